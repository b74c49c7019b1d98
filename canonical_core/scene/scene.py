"""Agg, streaming: the sparse voxel scene that folds one frame at a time.

Per voxel the scene keeps a running representative (its reliability, feature, lifted position and
colour) and the weighted sums of every fused field. A frame is folded in one vectorised pass
(`kernels.fold_kernel`); within the frame the paper's rule is exact.

Re-weighting rule when a more reliable observation replaces a voxel's representative: the sums
gathered so far were weighted by similarity to the *old* representative; they are scaled by
s = max(0, cos(F_old_rep, F_new_rep)) -- evidence that agreed with a representative that itself
disagrees with the new one is discounted as a whole, and evidence consistent with both is kept.
Where a voxel's representative never changes after its first frame this equals `aggregate_batch`
to float tolerance; elsewhere the deviation is measured by the tests and the fold benchmark.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import itertools
import json
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..camera import Camera
from ..evidence import AppearanceUncertainty, denoise_rough_depth, extract_evidence, observation_sh_basis, sensor_depth_std
from ..evidence.mvs import (SourceView, SourceWindow, complete_depth, depth_range_from_points, estimate_depth,
                            sensor_holes)
from ..decode import GaussianDecoder, solve_colours, support_unit
from ..frame import Frame, check_rgb_only, depth_warnings
from ..gaussians import Gaussians
from .config import SceneConfig
from .decoded import DecodedRows
from .fields import fields_from_sums, sh_sum_widths
from .keyframes import Keyframes, view_from_arrays, view_to_arrays
from .free_space import (CHUNK, SeeThroughHistory, frame_free_space_kernel, history_free_space_kernel, see_through_map,
                         update_chunk_boxes_kernel)
from .kernels import VoxelRows, fold_kernel, rebuild_table_kernel, resolve_kernel, voxel_keys_kernel

FORMAT_NAME = "canonicalgs-scene"
FORMAT_VERSION = 4  # 4 adds the per-view observation density (v3 files load with a density of 1)


class CapacityError(ValueError):
    """A fold would take the scene past ``SceneConfig.max_voxels``; the scene is unchanged."""


class DecodeInputs(NamedTuple):
    """A scene's state as `Scene.decode_from` reads it (`Scene.decode_inputs`: copies)."""

    sums: dict[str, np.ndarray]  # `Scene.sums`, as views into one copy of the scene's state
    observations_per_view: float  # `Scene.observations_per_view`
    views: list[Frame]  # the colour solve's kept input views (empty when it is off)
    # [V] per row, the stamp of the fold that last changed its sums (`decoded`); None: decode every row afresh
    changed_at: np.ndarray | None = None


@dataclass(frozen=True)
class FoldReport:
    """What one `Scene.fold` call did.

    ``frame_index`` is the frame's arrival index. A frame without depth and without a usable source
    view yet is ``pending``: accepted and kept, and folded (its depth estimated) by the call whose
    frame gives it a partner; that call counts it in ``also_folded``. ``denoised``: the frame's depth
    was far rougher than its noise model and was folded as its local median (`evidence.denoise`).
    ``warnings``: problems with the input that did not stop the fold, each ``"field: problem"``
    (e.g. depth that gave no observation).
    """

    frame_index: int
    observations: int
    new_voxels: int
    updated_voxels: int
    representative_switches: int
    ms: float
    pending: bool = False
    also_folded: int = 0
    completed_pixels: int = 0
    denoised: bool = False
    warnings: list[str] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


# fold stamps, unique in the process: inputs of one scene can never match another scene's decoded rows
_STAMPS = itertools.count(1)

MAX_TABLE_LOAD = 0.7  # linear probing stays at ~2 probes per hit up to here, and the table at <= 12 B/voxel


def _next_pow2(n: int) -> int:
    return 1 << max(4, int(n - 1).bit_length())


def _table_size(n_voxels: int) -> int:
    return _next_pow2(int(n_voxels / MAX_TABLE_LOAD) + 1)


class Scene:
    """A streaming CanonicalGS scene.

    Example:
        >>> scene = Scene(SceneConfig(voxel_size=0.01))
        >>> len(scene), scene.frames
        (0, 0)
    """

    # per-voxel arrays beside the float32 record (`VoxelRows`): name -> (dtype, trailing shape)
    _ARRAYS = {
        "keys": (np.int64, ()),
        "rep_rgb": (np.uint8, (3,)),  # input colours are 8-bit: lossless
        "free": (np.float32, ()),  # written by the free-space kernels, which scan it with the keys
        "n_obs": (np.int32, ()),
    }

    def __init__(self, config: SceneConfig, initial_capacity: int = 1 << 15):
        if not isinstance(config, SceneConfig):
            raise ValueError(f"config: expected a SceneConfig, got {type(config).__name__}")
        self.config = config
        self.appearance = AppearanceUncertainty(config.feature_dim)
        self.decoder = GaussianDecoder(config.feature_dim, opacity_slope=config.opacity_slope, opacity_bias=config.opacity_bias)
        self.frames = 0
        self._layout = VoxelRows(config.feature_dim, sh_sum_widths(config.sh_degree))
        self._n = 0
        self._density_sum, self._density_frames = 0.0, 0  # observations per touched voxel, summed over folds
        self._state = self._allocate(initial_capacity)
        self._table = np.full(_table_size(initial_capacity), -1, np.int32)
        self._scratch_m = 0
        self._chunk_lo = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
        self._chunk_hi = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
        self._history = SeeThroughHistory(config.free_space_history)
        self._window = SourceWindow(config.source_window)
        # frames without depth that wait for a partner, with their window view (None after loading
        # a snapshot: recomputed when the frame is folded)
        self._pending: list[tuple[Frame, SourceView | None]] = []
        self._keyframes = Keyframes(config.colour_solve_views, config.colour_solve_scale)  # the colour solve's views
        # per row, the stamp of the fold that last changed its sums; the decode reuses what it decoded
        # from sums of the same stamp (`decoded`). Derived state: not in snapshots.
        self._changed_at = np.zeros(self.capacity, np.int64)
        self._decoded: DecodedRows | None = None
        self._decoded_lock = threading.Lock()

    # -- state management ---------------------------------------------------------------------
    @property
    def label_dim(self) -> int:
        return self._layout.label_dim

    def _allocate(self, capacity: int) -> dict[str, np.ndarray]:
        state = {name: np.zeros((capacity, *shape), dtype) for name, (dtype, shape) in self._ARRAYS.items()}
        state["rows"] = np.zeros((capacity, self._layout.width), np.float32)
        return state

    @property
    def capacity(self) -> int:
        return int(self._state["keys"].shape[0])

    def _reserve(self, n_voxels: int) -> None:
        """Grow the rows (x1.5, amortised) and the hash table (load <= MAX_TABLE_LOAD) to hold ``n_voxels``."""
        if n_voxels > self.capacity:
            new = self._allocate(max(n_voxels, int(self.capacity * 1.5)))
            for name, arr in self._state.items():
                new[name][: self._n] = arr[: self._n]
            self._state = new
            changed_at = np.zeros(self.capacity, np.int64)
            changed_at[: self._n] = self._changed_at[: self._n]
            self._changed_at = changed_at
            for name in ("_chunk_lo", "_chunk_hi"):
                grown = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
                grown[: getattr(self, name).shape[0]] = getattr(self, name)
                setattr(self, name, grown)
        if n_voxels > MAX_TABLE_LOAD * self._table.shape[0]:
            self._table = np.empty(_table_size(n_voxels), np.int32)
            rebuild_table_kernel(self._table, self._state["keys"], self._n)

    def _set_label_dim(self, S: int) -> None:
        """Widen every row by the label columns (zero so far) once the first frame with S labels arrives."""
        old = self._layout
        self._layout = VoxelRows(self.config.feature_dim, sh_sum_widths(self.config.sh_degree), S)
        rows = np.zeros((self.capacity, self._layout.width), np.float32)
        rows[:, : old.width] = self._state["rows"]  # the label columns come last
        self._state["rows"] = rows

    def _scratch(self, m: int) -> None:
        if m > self._scratch_m or not self._scratch_m:  # allocated on first use, even for a frame with no evidence
            self._scratch_m = max(m, 1024)
            self._obs_keys = np.empty(self._scratch_m, np.int64)
            self._frame_keys = np.empty(self._scratch_m, np.int64)
            self._new_keys = np.empty(self._scratch_m, np.int64)
            self._touched = np.empty(self._scratch_m, np.int32)
            self._best = np.empty(self._scratch_m, np.int32)
            self._feat_inv_norm = np.empty(self._scratch_m, np.float32)
            self._rep_inv_norm = np.empty(self._scratch_m, np.float32)
            self._head = np.empty(self._scratch_m, np.int32)
            self._tail = np.empty(self._scratch_m, np.int32)
            self._next_obs = np.empty(self._scratch_m, np.int32)
            self._local_table = np.empty(_next_pow2(2 * self._scratch_m), np.int32)

    # -- folding ------------------------------------------------------------------------------
    def fold(self, frame: Frame) -> FoldReport:
        """Fold one frame into the scene. Raises ValueError (the scene unchanged) on bad input.

        Frames without depth get it from a plane sweep against the session's recent views (its
        uncertainty becomes the frame's depth std, so reliability follows as with sensor depth).
        """
        t0 = time.perf_counter()
        if not isinstance(frame, Frame):
            raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
        if frame.depth is None:
            return self._fold_without_depth(frame, t0)
        frame, denoised = self._denoised(frame)
        view, completed = None, 0
        if self.config.depth_completion:
            self._check_foldable(frame)  # before the sweep's cost
            view = self._window.view_of(frame)
            sources = self._sources_for(frame.camera)
            if sources:
                frame, completed = self._completed(frame, sources, view)
        counts = self._fold_with_depth(frame)
        if view is not None:
            self._window.add(view)  # after the fold: a frame that fails to fold leaves the window as it was
        self._keyframes.add(self.frames, frame)
        self.frames += 1
        warnings = depth_warnings(frame.depth, self.config.near, self.config.far) if counts[0] == 0 else []
        return FoldReport(self.frames - 1, *counts, ms=(time.perf_counter() - t0) * 1000.0, completed_pixels=completed,
                          denoised=denoised, warnings=warnings)

    def _denoised(self, frame: Frame) -> tuple[Frame, bool]:
        """``frame`` with its depth replaced by the local median where it is far rougher than its
        noise model (`evidence.denoise`), and whether it was."""
        c = self.config
        depth = frame.depth.numpy()
        std = None if frame.depth_std is None else frame.depth_std.numpy()
        smooth, smooth_std = denoise_rough_depth(depth, std, c.depth_denoise_radius, c.depth_sigma0, c.depth_sigma2,
                                                 c.depth_sigma_ref)
        if smooth is depth:
            return frame, False
        return dataclasses.replace(frame, depth=torch.from_numpy(smooth), depth_std=torch.from_numpy(smooth_std)), True

    def _fold_with_depth(self, frame: Frame) -> tuple[int, int, int, int]:
        """(observations, new voxels, updated voxels, representative switches) of folding ``frame``."""
        ev = extract_evidence(frame, self.config, self.appearance)
        if ev.labels is not None and self.label_dim and ev.labels.shape[1] != self.label_dim:
            raise ValueError(f"labels: expected {self.label_dim} label channels (as earlier frames), got {ev.labels.shape[1]}")
        m = len(ev)
        self._scratch(m)
        obs_keys, new_keys = self._obs_keys[:m], self._new_keys[:m]
        inv_voxel = np.float32(1.0 / self.config.voxel_size)
        voxel_keys_kernel(ev.points, inv_voxel, obs_keys)
        n_touched, n_new, n_obs = resolve_kernel(
            obs_keys, ev.reliability, self.config.uses_reliability, self._table, self._state["keys"],
            self._local_table[: _next_pow2(2 * m)], self._frame_keys, self._touched, new_keys, self._best, self._head,
            self._tail, self._next_obs)
        cap = self.config.max_voxels
        if cap is not None and self._n + n_new > cap:
            raise CapacityError(
                f"max_voxels: folding this frame would grow the scene to {self._n + n_new} voxels, above the cap of {cap}"
            )
        # nothing has changed up to here; from here on the fold cannot fail on input
        if ev.labels is not None and not self.label_dim:
            self._set_label_dim(ev.labels.shape[1])
        self._reserve(self._n + n_new)
        s = self._state
        labels = ev.labels if ev.labels is not None else np.zeros((m, self.label_dim), np.float32)
        basis = observation_sh_basis(ev, frame.camera, self.config.sh_degree)
        switches = fold_kernel(
            self._table, s["keys"], s["rows"], s["rep_rgb"], s["n_obs"], self._n, self._layout.offsets(),
            self.config.uses_reliability, self.config.uses_similarity, inv_voxel,
            n_touched, self._touched, new_keys, n_new, self._best, self._head, self._next_obs,
            ev.reliability, ev.features, ev.colors, ev.points, basis, labels, ev.labels is not None,
            self._feat_inv_norm[:m], self._rep_inv_norm[:m],
        )
        update_chunk_boxes_kernel(s["keys"], self._n, self._n + n_new, self._chunk_lo, self._chunk_hi)
        stamp = next(_STAMPS)
        touched = self._touched[:n_touched]
        self._changed_at[touched[touched >= 0]] = stamp
        self._changed_at[self._n: self._n + n_new] = stamp
        if self.config.free_space:
            self._fold_free_space(frame, self._n, self._n + n_new)
        self._n += n_new
        if n_touched:
            self._density_sum += n_obs / n_touched
            self._density_frames += 1
        return int(n_obs), int(n_new), int(n_touched - n_new), int(switches)

    def _check_foldable(self, frame: Frame) -> None:
        """The checks evidence extraction makes that do not need depth (so a waiting frame cannot fail later)."""
        if self.config.feature_backend == "client" and frame.features is None:
            raise ValueError("features: this session uses client-supplied features, but the frame carries none")
        if frame.labels is not None and self.label_dim and frame.labels.shape[-1] != self.label_dim:
            raise ValueError(f"labels: expected {self.label_dim} label channels (as earlier frames), got {frame.labels.shape[-1]}")

    def _sources_for(self, camera: Camera):
        """Source views for a sweep at ``camera`` (never its own view: selection needs a baseline)."""
        return self._window.select(camera, k=self.config.depth_sources)

    def _with_estimated_depth(self, frame: Frame, sources, view=None, where=None) -> Frame:
        near_far = None
        if self._n:  # the swept range from what the scene already holds (a subsample is enough)
            step = max(1, self._n // 20_000)
            near_far = depth_range_from_points(frame.camera, self._layout.field(self._state["rows"][: self._n: step], "rep_pos"))
        near, far = near_far if near_far is not None else (None, None)
        depth, std = estimate_depth(frame, sources, near=near, far=far, num_hypotheses=self.config.depth_hypotheses,
                                    reference=view, where=where)
        return dataclasses.replace(frame, depth=torch.from_numpy(depth), depth_std=torch.from_numpy(std))

    def _completed(self, frame: Frame, sources, view: SourceView) -> tuple[Frame, int]:
        """``frame`` with the large holes of its depth filled by the sweep (`complete_depth`), and
        the number of pixels filled."""
        c = self.config
        holes = sensor_holes(frame.depth.numpy(), c.depth_completion_radius)
        if not holes.any():
            return frame, 0
        swept = self._with_estimated_depth(frame, sources, view, where=holes)  # only the holes are swept
        std = frame.depth_std if frame.depth_std is not None else sensor_depth_std(
            frame.depth, c.depth_sigma0, c.depth_sigma2, c.depth_sigma_ref)
        depth, std, filled = complete_depth(frame.depth.numpy(), std.numpy(), swept.depth.numpy(),
                                            swept.depth_std.numpy(), holes)
        if not filled.any():  # the frame as it came: its evidence is then bit-identical to a plain fold
            return frame, 0
        return dataclasses.replace(frame, depth=torch.from_numpy(depth), depth_std=torch.from_numpy(std)), int(filled.sum())

    def _fold_without_depth(self, frame: Frame, t0: float) -> FoldReport:
        self._check_foldable(frame)
        check_rgb_only(frame)
        index = self.frames
        sources = self._sources_for(frame.camera)
        if not sources and len(self._pending) >= self.config.source_window:
            raise ValueError(f"depth: the frame has no depth and no earlier view overlaps it, and "
                             f"{len(self._pending)} frames already wait for a partner")
        view = self._window.view_of(frame)  # matching features once: the sweep's reference and the window's view
        if not sources:
            self._window.add(view)
            self._pending.append((frame, view))
            self._keyframes.add(index, frame)  # its colours join the scene once a partner arrives
            self.frames += 1
            return FoldReport(index, 0, 0, 0, 0, ms=(time.perf_counter() - t0) * 1000.0, pending=True)
        estimated = self._with_estimated_depth(frame, sources, view)
        counts = self._fold_with_depth(estimated)
        self._window.add(view, depth=estimated.depth)
        self._keyframes.add(index, frame)
        self.frames += 1
        also = 0
        for entry in list(self._pending):  # frames that waited for a partner: fold them now, in order
            waiting, waiting_view = entry
            waiting_sources = self._sources_for(waiting.camera)
            if waiting_sources:
                self._fold_with_depth(self._with_estimated_depth(waiting, waiting_sources, waiting_view))
                self._pending.remove(entry)
                also += 1
        return FoldReport(index, *counts, ms=(time.perf_counter() - t0) * 1000.0, also_folded=also)

    def _fold_free_space(self, frame: Frame, first_new: int, n_voxels: int) -> None:
        """The frame's see-through evidence for every voxel in its frustum (the new ones included),
        then the earlier frames' evidence for the voxels this frame created (see free_space.py)."""
        m = see_through_map(frame, self.config)
        s, voxel, near = self._state, np.float32(self.config.voxel_size), np.float32(self.config.near)
        frame_free_space_kernel(s["keys"], s["free"], self._chunk_lo, self._chunk_hi, n_voxels, voxel, m.w2c,
                                m.intrinsics, m.threshold, m.weight, np.float32(m.area_scale), near)
        h = self._history
        if h.count and n_voxels > first_new:
            history_free_space_kernel(s["keys"], s["free"], first_new, n_voxels, voxel, h.order(), h.w2c, h.intrinsics,
                                      h.threshold, h.weight, h.dims, h.area, near)
        h.push(m)

    # -- reading ------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self._n

    def sums(self) -> dict[str, np.ndarray]:
        """The raw per-voxel sums (contiguous copies, insertion order, scratch excluded)."""
        return {name: array.copy() for name, array in self._sums_of(self._state).items()}

    def _copied_sums(self) -> dict[str, np.ndarray]:
        """`sums`, as views into one copy of the state: one block copy of the rows instead of a
        strided copy per column (5x faster, and it is what a service does under the session lock)."""
        return self._sums_of({k: v[: self._n].copy() for k, v in self._state.items()})

    def _sums_of(self, state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The sums as views into ``state`` (the scene's arrays or a copy of them), its first `len(self)` rows."""
        n = self._n
        rows = state["rows"][:n]
        out = {k: v[:n] for k, v in state.items() if k != "rows"}
        out |= {name: self._layout.field(rows, name) for name in self._layout.columns}
        if not self.label_dim:  # the fields' contract: label_sum is [V, 0] without labels
            out["label_sum"] = np.zeros((n, 0), np.float32)
        return out

    def _set_sums(self, sums: dict[str, np.ndarray]) -> None:
        """Inverse of `sums` on a fresh scene with enough capacity (snapshot loading)."""
        n = len(sums["keys"])
        for name in self._ARRAYS:
            self._state[name][:n] = sums[name]
        for name in self._layout.columns:
            self._layout.field(self._state["rows"][:n], name)[...] = sums[name]
        self._n = n
        self._changed_at[:n] = next(_STAMPS)

    def fields(self, sort: bool = True) -> dict[str, torch.Tensor]:
        """Scene fields (see `fields_from_sums`), sorted by voxel key unless ``sort=False``."""
        return fields_from_sums(self.sums(), self.config, sort=sort)

    def observations_per_view(self) -> float:
        """Mean observations one frame adds to a voxel it touches (pixels per voxel footprint, holes
        included). With `support_unit` it makes R_scene's decoding unit "one typical view", so opacity
        does not depend on image resolution or voxel size, only on how many views support a voxel."""
        return self._density_sum / self._density_frames if self._density_frames else 1.0

    def decode_inputs(self) -> DecodeInputs:
        """What `decode_from` needs of the scene, copied: later folds do not change it. Cheap next to
        the decode itself (a copy of the sums), so a caller that guards the scene with a lock can
        hold it for this alone and decode outside it."""
        return DecodeInputs(self._copied_sums(), self.observations_per_view(), self._keyframes.frames(),
                            self._changed_at[: self._n].copy())

    def decode(self, max_gaussians: int | None = None, min_support: float = 0.0) -> Gaussians:
        """Gaussians of every voxel with R_scene > ``min_support``; with ``max_gaussians``, the
        best-supported ones (level of detail). With ``colour_solve_views``, their colours are then
        solved against the kept input views (`decode.solve_colours`). The same as
        ``decode_from(decode_inputs(), ...)``."""
        return self.decode_from(self.decode_inputs(), max_gaussians, min_support)

    def decode_from(self, inputs: DecodeInputs, max_gaussians: int | None = None, min_support: float = 0.0) -> Gaussians:
        """`decode` of the scene as it was when ``inputs`` were taken (`decode_inputs` of this scene).

        Each decode keeps what it made of every voxel (`scene.decoded.DecodedRows`, about 160 bytes
        a voxel), and the next one decodes again only the voxels whose sums a fold has changed since;
        opacities, which depend on the scene-wide support unit and on free space, are recomputed for
        all. So a decode after a fold costs what the fold touched, not the scene (about 4x less at 204k
        voxels, `bench/decode.py`), and equals a decode from scratch (``inputs._replace(changed_at=None)``).
        Decodes of one scene take turns (they share those rows); folds do not wait for them.
        """
        if max_gaussians is not None and max_gaussians < 0:
            raise ValueError(f"max_gaussians: expected a non-negative integer, got {max_gaussians}")
        if min_support < 0:
            raise ValueError(f"min_support: expected >= 0, got {min_support}")
        # which voxels decode is known from the raw sums (R_scene, free space): the fields, and the
        # per-voxel SH solve among them, are then computed for those rows alone
        reliability = torch.as_tensor(inputs.sums["r_sum"])
        unit = support_unit(reliability, torch.as_tensor(inputs.sums["n_obs"])) * inputs.observations_per_view
        supported = reliability > min_support
        if self.config.free_space:  # voxels that more rays saw through than saw at are not surface
            supported &= torch.as_tensor(inputs.sums["free"]) <= self.config.free_space_dominance * reliability
        keep = torch.nonzero(supported).squeeze(1)
        if max_gaussians is not None and keep.numel() > max_gaussians:
            top = torch.argsort(reliability[keep], descending=True, stable=True)[:max_gaussians]
            keep = keep[torch.sort(top).values]
        with torch.no_grad():
            opacities = self.decoder.opacities(reliability[keep], torch.as_tensor(inputs.sums["free"])[keep], unit)
        gaussians = Gaussians(opacities=opacities, **self._shapes_and_colours(inputs, keep.numpy()))
        return solve_colours(gaussians, inputs.views) if inputs.views else gaussians

    def _shapes_and_colours(self, inputs: DecodeInputs, rows: np.ndarray) -> dict[str, torch.Tensor | None]:
        """`GaussianDecoder.shapes_and_colours` of ``rows``: reused from an earlier decode for the rows
        whose sums are unchanged since (`DecodedRows`), decoded from ``inputs`` for the rest. The
        fields (and the per-voxel SH solve among them) are computed for those rows alone."""
        d = self.decoder  # what else a row's decode depends on: label channels, the decoder's parameters and clamps
        key = (inputs.sums["label_sum"].shape[1], tuple((id(p), p._version) for p in d.parameters()),
               (d.min_thickness, d.min_extent, d.max_extent))
        with self._decoded_lock:  # decodes of one scene take turns: they share the decoded rows
            cache = self._decoded
            if cache is None or cache.key != key:
                cache = self._decoded = DecodedRows(key)
            stamps = inputs.changed_at[rows] if inputs.changed_at is not None else None
            todo = rows if stamps is None else rows[~cache.current(rows, stamps)]
            index = torch.from_numpy(todo)
            f = fields_from_sums({k: torch.as_tensor(v).index_select(0, index) for k, v in inputs.sums.items()},
                                 self.config, sort=False)
            with torch.no_grad():
                fresh = self.decoder.shapes_and_colours(f, self.config.voxel_size)
            if stamps is None:
                return fresh
            cache.store(todo, inputs.changed_at[todo], fresh)
            return fresh if len(todo) == len(rows) else cache.gather(rows)

    def _snapshot_arrays(self) -> dict[str, np.ndarray]:
        """Every array of the fused state: sums, free-space history, source window, waiting frames,
        the colour solve's kept views."""
        arrays = {f"state.{k}": v for k, v in self.sums().items()}
        arrays |= {f"history.{k}": v for k, v in self._history.to_arrays().items()}
        arrays |= {f"window.{k}": v for k, v in self._window.to_arrays().items()}
        for i, (f, _) in enumerate(self._pending):
            arrays |= view_to_arrays(f"pending.{i}", f)
            arrays |= {f"pending.{i}.{name}": getattr(f, name).numpy() for name in ("features", "labels") if getattr(f, name) is not None}
        if self._keyframes.capacity:  # scenes without the colour solve keep their earlier digests
            arrays |= {f"keyframes.{k}": v for k, v in self._keyframes.to_arrays().items()}
        return arrays

    def digest(self) -> str:
        """sha256 of the whole fused state (sums, free-space history, frame count): equal iff two
        scenes would decode and fold on identically."""
        h = hashlib.sha256(f"frames={self.frames}|labels={self.label_dim}|density={self._density_sum!r},{self._density_frames}|".encode())
        for name, array in sorted(self._snapshot_arrays().items()):
            h.update(f"{name}|{array.dtype.str}|{array.shape}|".encode())
            h.update(np.ascontiguousarray(array).tobytes())
        return h.hexdigest()

    def memory_bytes(self) -> int:
        decoded = self._decoded.nbytes() if self._decoded is not None else 0
        return int(sum(a.nbytes for a in self._state.values()) + self._table.nbytes + self._keyframes.nbytes()
                   + self._changed_at.nbytes + decoded)

    def bytes_per_voxel(self) -> float:
        """State bytes per stored voxel: one row of every per-voxel array plus the hash table's bytes
        per stored voxel (row slack reserved for growth is excluded; `memory_bytes` includes it)."""
        row = sum(a.itemsize * int(np.prod(a.shape[1:])) for a in self._state.values() if a.shape[0] == self.capacity)
        return row + self._table.nbytes / max(self._n, 1)

    def stats(self) -> dict:
        return {"frames": self.frames, "voxels": self._n, "memory_bytes": self.memory_bytes(),
                "capacity": self.capacity, "label_dim": self.label_dim}

    # -- persistence --------------------------------------------------------------------------
    def to_bytes(self) -> bytes:
        """One self-contained, versioned snapshot (an .npz with a JSON header)."""
        header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": self.config.to_dict(),
                  "frames": self.frames, "label_dim": self.label_dim, "voxels": self._n, "pending": len(self._pending),
                  "density": [self._density_sum, self._density_frames]}
        arrays = self._snapshot_arrays()
        for prefix, module in (("decoder", self.decoder), ("appearance", self.appearance)):
            for k, v in module.state_dict().items():
                arrays[f"{prefix}.{k}"] = v.detach().cpu().numpy()
        buf = io.BytesIO()
        np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
        return buf.getvalue()

    def save(self, path: str | os.PathLike) -> None:
        """Write the snapshot atomically (temp file, fsync, rename, fsync of the folder)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(self.to_bytes())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)  # the rename itself must survive a crash
        finally:
            os.close(folder)

    @classmethod
    def from_bytes(cls, data: bytes) -> "Scene":
        try:
            npz = np.load(io.BytesIO(data), allow_pickle=False)
            header = json.loads(npz["header"].tobytes().decode())
        except Exception as exc:  # any decoding failure means "not one of our snapshots"
            raise ValueError(f"snapshot: not a readable scene file ({exc})") from None
        if header.get("format") != FORMAT_NAME:
            raise ValueError(f"snapshot: unknown format {header.get('format')!r}")
        if header.get("version") not in (3, FORMAT_VERSION):
            raise ValueError(f"snapshot: version {header.get('version')} is not supported (expected 3 or {FORMAT_VERSION})")
        scene = cls(SceneConfig.from_dict(header["config"]), initial_capacity=max(int(header["voxels"]), 16))
        if header["label_dim"]:
            scene._set_label_dim(int(header["label_dim"]))
        n = int(header["voxels"])
        scene._set_sums({k[len("state."):]: npz[k] for k in npz.files if k.startswith("state.")})
        scene.frames = int(header["frames"])
        density_sum, density_frames = header.get("density", [0.0, 0])
        scene._density_sum, scene._density_frames = float(density_sum), int(density_frames)
        rebuild_table_kernel(scene._table, scene._state["keys"], n)
        update_chunk_boxes_kernel(scene._state["keys"], 0, n, scene._chunk_lo, scene._chunk_hi)
        scene._history = SeeThroughHistory.from_arrays(
            scene.config.free_space_history, {k[len("history."):]: npz[k] for k in npz.files if k.startswith("history.")})
        scene._window = SourceWindow.from_arrays({k[len("window."):]: npz[k] for k in npz.files if k.startswith("window.")})
        for i in range(int(header.get("pending", 0))):
            scene._pending.append((view_from_arrays(f"pending.{i}", npz, **{
                name: npz[f"pending.{i}.{name}"].copy() if f"pending.{i}.{name}" in npz.files else None
                for name in ("features", "labels")}), None))
        scene._keyframes = Keyframes.from_arrays(scene.config.colour_solve_views, scene.config.colour_solve_scale,
                                                 {k[len("keyframes."):]: npz[k] for k in npz.files if k.startswith("keyframes.")})
        for prefix, module in (("decoder", scene.decoder), ("appearance", scene.appearance)):
            module.load_state_dict({k: torch.from_numpy(npz[f"{prefix}.{k}"].copy()) for k in module.state_dict()})
        return scene

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Scene":
        return cls.from_bytes(Path(path).read_bytes())

    def __repr__(self) -> str:
        return f"Scene(frames={self.frames}, voxels={self._n}, voxel_size={self.config.voxel_size})"
