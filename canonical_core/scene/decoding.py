"""The decoder side of a scene: sums -> Gaussians, decoded once per change.

Three things live here, behind one lock (`SceneDecoding.lock`: decodes of one scene take turns):

- the decoder (`decode.GaussianDecoder`) and the colour solve against the kept input views
  (`decode.colour_offsets`) with its last solution (`ColourSolution`), which decodes reuse until
  `SceneConfig.colour_solve.refresh` frames were folded since, and which starts the next solve;
- the decoded rows (`decoded.DecodedRows`): what the last decode made of each voxel, with the
  change stamp of the sums it came from, so that a decode after a fold decodes again only the
  voxels whose sums changed; opacities, which depend on the scene-wide support unit and on free
  space, are recomputed for all;
- the decoded Gaussians of the scene as it is now, per level of detail (`Scene.gaussians`): a
  request for an unchanged scene is answered without decoding. These entries are read and written
  under the *scene's* lock (a fold drops them), so the decode itself runs outside it and a fold
  never waits for a decode.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable, Literal, NamedTuple

import numpy as np
import torch

from ..decode import GaussianDecoder, colour_offsets, with_colour_offsets
from ..frame import Frame
from ..gaussians import Gaussians
from ..config import SceneConfig
from .decoded import PARTS, DecodedRows, rounded
from .fields import decoder_fields
from .selection import DecodedRowSet, decoded_rows, scene_features, strongest
from .shapes import voxel_shapes

# conjugate-gradient steps of a colour solve that starts from the last solution (one from zero takes the
# library's default, 4): from a solution a handful of frames old, two reach about what a solve from zero does
REFRESH_ITERATIONS = 2
# "solve": a decode solves the colours when due (`SceneConfig.colour_solve.refresh`); "last": it shows
# the last solution and never solves, for a caller whose solves run elsewhere (`Scene.solve_colours`)
Colours = Literal["solve", "last"]
DECODE_CACHE_ENTRIES = 4  # levels of detail of one scene state kept decoded (the full decode always among them)


class DecodeInputs(NamedTuple):
    """A scene's state as a decode reads it: copies (`Scene.decode_inputs`), or views of the live
    state that `SceneDecoding.take` reads under the scene's lock (`Scene.gaussians`)."""

    sums: dict[str, np.ndarray]  # `Scene.sums`, as views into one copy of the scene's state (or into the state, live)
    # the sums of some rows ([N] int64) copied, whole records at a time (`sums.gathered_sums`)
    gather: Callable[[np.ndarray], dict[str, np.ndarray]]
    observations_per_view: float  # `Scene.observations_per_view`
    views: list[Frame]  # the colour solve's kept input views (empty when it is off)
    # [V] int32 per row, the stamp of the change that last changed its sums; None: decode every row afresh
    changed_at: np.ndarray | None = None
    frames: int = 0  # `Scene.frames`: when the colour solve is due again (`SceneConfig.colour_solve.refresh`)
    stamp_epoch: int = 0  # the epoch of those stamps (`stamps.StampClock`): the decoded rows of another are stale


class DecodeWork(NamedTuple):
    """One decode's share of a scene's state (`SceneDecoding.take`): the rows that decode and a copy of
    what the decode reads of them, so that it runs while later folds change the scene."""

    chosen: DecodedRowSet  # the rows that decode, their support and free-space evidence
    todo: np.ndarray  # [T] int64 rows of them decoded afresh (the decoded rows lack them)
    todo_sums: dict[str, np.ndarray]  # every sum of those rows, [T, ...]
    todo_stamps: np.ndarray | None  # [T] int32 their change stamps; None: a decode from scratch, not kept
    features: torch.Tensor | None  # [K, L] F_scene of every row that decodes, when some are reused and it is wanted
    wants_features: bool  # the Gaussians carry F_scene (False: features None, and F_scene of reused rows is not read)
    observations_per_view: float
    views: list[Frame]  # the colour solve's kept input views
    frames: int
    whole: bool  # every voxel that decodes (no level of detail, no support floor)


@dataclass(frozen=True, eq=False)  # compared by identity: arrays have no single truth value
class ColourSolution:
    """The colour solve's last answer: SH offsets of the voxel rows it solved.

    Kept narrow, whatever it is made from (a solve's float32 answer, int64 rows, an earlier
    snapshot's arrays): rows as int32 (a scene's rows fit: its hash table indexes them so, below
    `config.MAX_VOXELS`) and offsets as float16 (their rounding, 2^-11 relative, stays well under one
    step of 8-bit colour). Every decode shows them so rounded (`at`), so a solution fresh
    from a solve and one read back from a snapshot give the same Gaussians bit for bit."""

    rows: np.ndarray  # [M] int32 ascending
    offsets: torch.Tensor  # [M, K, 3] float16
    frames: int  # the scene's frame count when solved

    def __post_init__(self):
        object.__setattr__(self, "rows", np.array(self.rows, np.int32))  # its own copy
        object.__setattr__(self, "offsets", self.offsets.detach().to(torch.float16))
        object.__setattr__(self, "frames", int(self.frames))

    def at(self, rows: np.ndarray) -> torch.Tensor:  # [N] int64 ascending -> [N, K, 3] float32: zeros where unsolved
        """The offsets of ``rows``; rows it did not solve (decoded since) get none."""
        out = torch.zeros(len(rows), *self.offsets.shape[1:])
        if len(self.rows):
            at = np.minimum(np.searchsorted(self.rows, rows), len(self.rows) - 1)
            hit = self.rows[at] == rows
            out[torch.from_numpy(hit)] = self.offsets[torch.from_numpy(at[hit])].float()
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"rows": self.rows, "offsets": self.offsets.numpy(), "frames": np.asarray(self.frames, np.int64)}

    @classmethod
    def from_arrays(cls, arrays) -> "ColourSolution":  # also an earlier snapshot's int64 rows and float32 offsets
        return cls(np.asarray(arrays["rows"]), torch.from_numpy(np.array(arrays["offsets"])), int(arrays["frames"]))

    def nbytes(self) -> int:
        return self.rows.nbytes + self.offsets.numel() * self.offsets.element_size()


def check_decode_arguments(max_gaussians, min_support) -> None:
    """Raise ValueError naming ``max_gaussians`` unless it is None or an integer >= 0, and naming
    ``min_support`` unless it is a number >= 0 (infinity included: nothing decodes; NaN is refused,
    which every comparison would take as no support at all)."""
    integer = not isinstance(max_gaussians, bool) and isinstance(max_gaussians, (int, np.integer))
    if max_gaussians is not None and not (integer and max_gaussians >= 0):
        raise ValueError(f"max_gaussians: expected a non-negative integer or None, got {max_gaussians!r}")
    if (isinstance(min_support, bool) or not isinstance(min_support, (int, float, np.integer, np.floating))
            or not min_support >= 0):
        raise ValueError(f"min_support: expected >= 0 (a number), got {min_support!r}")


class SceneDecoding:
    """The decoder, its decoded rows and the decoded Gaussians of one scene (see the module)."""

    def __init__(self, config: SceneConfig):
        self.config = config
        self.decoder = GaussianDecoder(config.features.dim, opacity_slope=config.decoder.opacity_slope,
                                       opacity_bias=config.opacity_bias)
        self.lock = threading.Lock()  # taken before the scene's lock, never after
        self._rows: DecodedRows | None = None
        self._gaussians: dict = {}  # (level of detail, decoder key) -> Gaussians of the current state
        self.solution: ColourSolution | None = None  # the colour solve's last answer (snapshots keep it)
        self.epoch = 0  # bumped by `reset`: a solve started on the replaced state is not kept (`land`)

    def key(self) -> tuple:
        """What a row's decode depends on besides its sums: the decoder's parameters and clamps."""
        d = self.decoder
        return tuple((id(p), p._version) for p in d.parameters()), (d.min_thickness, d.min_extent, d.max_extent)

    # -- the decoded Gaussians of the current state (callers hold the scene's lock) ---------------
    def cached(self, lod: int | None, features: bool = True) -> Gaussians | None:
        """The kept Gaussians of ``lod``; without ``features``, those with features serve too."""
        hit = self._gaussians.get((lod, True, self.key()))
        return hit if hit is not None or features else self._gaussians.get((lod, False, self.key()))

    def keep(self, lod: int | None, gaussians: Gaussians) -> None:
        """Keep ``gaussians`` for ``lod``: Gaussians of an earlier decoder go (no request finds them
        again), then, past `DECODE_CACHE_ENTRIES`, a level of detail before a full decode, the oldest first."""
        decoder = self.key()
        for stale in [k for k in self._gaussians if k[2] != decoder]:
            del self._gaussians[stale]
        key = (lod, gaussians.features is not None, decoder)
        if key not in self._gaussians and len(self._gaussians) >= DECODE_CACHE_ENTRIES:
            self._gaussians.pop(min(self._gaussians, key=lambda k: k[0] is None))  # the first level of detail, else the oldest
        self._gaussians[key] = gaussians

    def forget(self) -> None:
        """The scene changed: its decoded Gaussians are stale."""
        self._gaussians.clear()

    def reset(self, keep_rows: bool = False) -> None:
        """The scene's state was replaced by a re-fold: its decoded rows are stale too (their stamps
        belong to the old voxel map), unless ``keep_rows``: the state was rolled back in place, and
        the map restamped the rows it restored, so the stamps still tell which decoded rows hold.
        Callers hold `lock` and the scene's lock."""
        if not keep_rows:
            self._rows = None
        self._gaussians.clear()
        self.solution = None
        self.epoch += 1

    # -- decoding -----------------------------------------------------------------------------
    def decode(self, inputs: DecodeInputs, max_gaussians: int | None = None, min_support: float = 0.0,
               features: bool = True) -> Gaussians:
        """Gaussians of every voxel of ``inputs`` with R_scene > ``min_support``; with
        ``max_gaussians``, the best-supported ones; with kept views, colours solved against them;
        without ``features``, no F_scene channels (`take`)."""
        with self.lock:  # decodes of one scene take turns: they share the decoded rows
            return self.finish(self.take(inputs, max_gaussians, min_support, features))

    def take(self, inputs: DecodeInputs, max_gaussians: int | None = None, min_support: float = 0.0,
             features: bool = True) -> DecodeWork:
        """The first half of a decode, for a caller that holds `lock`: which rows decode, and a copy of
        what the decode reads of their sums (all sums of the rows the decoded rows lack, F_scene of the
        others). ``inputs`` may view the scene's live state (`Scene.gaussians`, under the scene's lock):
        the work holds nothing of it, so `finish` runs while later folds change it.

        Without ``features`` the Gaussians carry no F_scene (features None), for callers that draw
        colour, depth or labels only: F_scene of the reused rows is then not read, which is most of
        what a decode after a fold reads of the scene (16 floats of every decoded row)."""
        check_decode_arguments(max_gaussians, min_support)
        # which voxels decode is known from the raw sums (R_scene, free space): the fields, and the
        # per-voxel SH solve among them, are then computed for those rows alone
        chosen = decoded_rows(inputs.sums, min_support, self.config)
        whole = min_support == 0  # every voxel that decodes: the scene's colours may be solved and kept
        if max_gaussians is not None and len(chosen.rows) > max_gaussians:
            whole = False
            top = strongest(chosen.support.numpy(), max_gaussians)
            chosen = chosen._replace(rows=chosen.rows[top], support=chosen.support[top], free=chosen.free[top])
        rows = chosen.rows
        # label channels change a row's decode too; stamps of another epoch may repeat this one's
        labels = inputs.sums.get("label_mean", inputs.sums.get("label_sum"))  # stored as means ([V, 0] without labels)
        key = (labels.shape[1], inputs.stamp_epoch, *self.key())
        if self._rows is None or self._rows.key != key:
            self._rows = DecodedRows(key)
        todo, stamps = rows, None
        if inputs.changed_at is not None:
            stamps = inputs.changed_at[rows]
            fresh = ~self._rows.current(rows, stamps)
            todo, stamps = rows[fresh], stamps[fresh]
        reused_features = features and len(todo) < len(rows)
        return DecodeWork(
            chosen, todo, inputs.gather(todo), stamps,
            scene_features(inputs.sums, rows, self.config.research.eps) if reused_features else None, features,
            inputs.observations_per_view, list(inputs.views), inputs.frames, whole,
        )  # fmt: skip

    def finish(self, work: DecodeWork, colours: Colours = "solve") -> Gaussians:
        """The second half of a decode (`take`), for a caller that holds `lock`. With ``colours``
        ``"last"`` it never solves: it shows the last solution (`_colour_offsets`), for a caller whose
        solves run elsewhere (`Scene.solve_colours`)."""
        gaussians = self.base(work)
        if not work.views or (colours == "last" and self.solution is None):  # nothing solved: the fused colours
            return gaussians
        return with_colour_offsets(gaussians, self._colour_offsets(gaussians, work.chosen.rows, work, colours))

    def base(self, work: DecodeWork) -> Gaussians:
        """`finish` before the colour solve: the decoded Gaussians in their fused colours."""
        if self.config.voxel_size is None:  # no frame has chosen it (`choices`): no voxel to decode
            return Gaussians.empty(self.config.sh_degree, self.config.features.dim if work.wants_features else None)
        chosen = work.chosen
        with torch.no_grad():
            opacities = self.decoder.opacities(chosen.support, chosen.free, chosen.unit * work.observations_per_view)
        return Gaussians(opacities=opacities, **self._shapes_and_colours(work))

    def refresh_due(self, frames: int) -> bool:
        """Whether a decode with ``colours="solve"`` of a scene at ``frames`` solves (views kept): no
        solution yet, or `SceneConfig.colour_solve.refresh` frames folded since the last one."""
        return self.solution is None or frames - self.solution.frames >= self.config.colour_solve.refresh

    def _colour_offsets(self, gaussians: Gaussians, rows: np.ndarray, work: DecodeWork, colours: Colours) -> torch.Tensor:
        """The colour solve's offsets of the decoded ``rows`` ([N, K, 3]): the last solution's while it
        is fresh (fewer than `SceneConfig.colour_solve.refresh` frames folded since), for a decode
        of part of the scene (a level of detail or a support floor, which never replaces the whole
        scene's solution) and with ``colours="last"``; else solved, from the last solution where there
        is one, and kept."""
        solution = self.solution
        last = solution.at(rows) if solution is not None else None
        if solution is not None and (colours == "last" or not (work.whole and self.refresh_due(work.frames))):
            return last
        if solution is None:
            offsets = colour_offsets(gaussians, work.views)
        else:
            offsets = colour_offsets(gaussians, work.views, last, iterations=REFRESH_ITERATIONS)
        solved = ColourSolution(rows, offsets, work.frames)  # rounded as it is kept, kept or not
        if work.whole:
            self.solution = solved
        return solved.offsets.float()

    def land(self, solution: ColourSolution, epoch: int) -> bool:
        """Keep ``solution`` (of the state at ``epoch``, `Scene.solve_colours`) unless a correction
        replaced that state meanwhile or a solution as new is kept; the caller holds `lock`."""
        if epoch != self.epoch or (self.solution is not None and self.solution.frames >= solution.frames):
            return False
        self.solution = solution
        return True

    def _shapes_and_colours(self, work: DecodeWork) -> dict[str, torch.Tensor | None]:
        """`GaussianDecoder.shapes_and_colours` of the rows that decode: decoded from the work's sums
        for the rows the decoded rows lack (then kept there), reused for the rest."""
        todo, sums = work.todo, work.todo_sums
        with torch.no_grad():
            # F_scene only where the Gaussians carry it or the decoder's heads read it
            f = decoder_fields(sums, self.config, work.wants_features or not self.decoder.heads_add_nothing())
            base = voxel_shapes(sums, np.arange(len(todo)), self.config.voxel_size, self.config.research.eps, self.decoder)
            fresh = rounded(self.decoder.shapes_and_colours(f, self.config.voxel_size, base))
        if not work.wants_features:
            fresh["features"] = None
        if work.todo_stamps is None:
            return fresh
        self._rows.store(todo, work.todo_stamps, {k: v for k, v in fresh.items() if k in PARTS})
        if len(todo) == len(work.chosen.rows):
            return fresh
        return self._rows.gather(work.chosen.rows) | {"features": work.features}

    def nbytes(self) -> int:
        """Bytes of the decoded rows and the colour solution (the cached Gaussians are shared with
        callers and not counted)."""
        return ((self._rows.nbytes() if self._rows is not None else 0)
                + (self.solution.nbytes() if self.solution is not None else 0))
