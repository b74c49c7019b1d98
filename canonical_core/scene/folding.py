"""One frame's fold into a scene's state, and the `FoldReport` of what it did.

One frame's route through `Scene.fold` goes one way:

    depth front end (`depth_frontend`: denoise, hole completion, plane sweep, pending frames)
      -> evidence (`evidence.extract_evidence`)
      -> integration into the voxel map (`integrate.integrate`, `voxel_map.VoxelMap`)
      -> free space (`integrate.integrate_free_space`)

Around it, the bookkeeping that makes a fold undoable and re-foldable: its undo record (`undo`),
the frame kept for corrections (`refold`) and a checkpoint where one is due (`snapshot`). The
functions here expect the caller to hold the scene's lock (`Scene` takes it).
"""

from __future__ import annotations

import functools
import time

import numpy as np
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, NamedTuple

from ..evidence import FrameEvidence, extract_evidence, observation_sh_basis
from ..evidence.extract import check_client_features
from ..frame import Frame, depth_warnings
from ..config import SceneConfig
from . import snapshot
from .choices import choose_settings
from .depth_frontend import Prepared, denoised_depth
from .integrate import integrate, integrate_free_space
from .keyframes import kept_view
from .undo import FoldUndo, history_slot, undo_folds

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["FoldReport", "PreparedFrame", "fold_cost", "fold_kept", "prepare"]


@dataclass(frozen=True)
class FoldReport:
    """What one `Scene.fold` call did.

    ``frame_index`` is the frame's arrival index. A frame without depth and without a usable source
    view yet is ``pending``: accepted and kept, and folded (its depth estimated) by the call whose
    frame gives it a partner; that call counts it in ``also_folded``. ``denoised``: the frame's depth
    was far rougher than its noise model and was folded as its local median (`evidence.denoise`).
    ``warnings``: problems with the input that did not stop the fold, each ``"field: problem"``
    (e.g. depth that gave no observation). ``sensor``: the sensor family whose noise model the scene
    uses, ``sensor_chosen`` why (`choices`). The ``description`` metadata reaches the HTTP schema.
    """

    frame_index: int = field(metadata={"description": "the frame's arrival index in the session"})
    observations: int = field(metadata={"description": "pixels folded"})
    new_voxels: int = field(metadata={"description": "voxels the frame created"})
    updated_voxels: int = field(metadata={"description": "existing voxels the frame touched"})
    representative_switches: int = field(metadata={"description": "voxels whose representative this frame replaced"})
    ms: float = field(metadata={"description": "the library's fold time, milliseconds"})
    pending: bool = field(default=False, metadata={"description": "a frame without depth waiting for a partner view (folded later)"})
    also_folded: int = field(default=0, metadata={"description": "earlier waiting frames this call folded"})
    completed_pixels: int = field(default=0, metadata={
        "description": "pixels whose missing depth the plane sweep filled (depth_completion)"})
    denoised: bool = field(default=False, metadata={
        "description": "the frame's depth was far rougher than its noise model and was replaced by a local median"})
    warnings: list[str] = field(default_factory=list, metadata={
        "description": "problems with the input that did not stop the fold, each 'field: problem'"})
    sensor: str | None = field(default=None, metadata={
        "description": "the depth sensor family whose noise model the scene uses (setting sensor.family)"})
    sensor_chosen: str | None = field(default=None, metadata={
        "description": "why that family: 'set', 'detected from depth quantisation (...)' or 'default: ...'"})

    def to_dict(self) -> dict:
        return asdict(self)


class PreparedFrame(NamedTuple):
    """A frame with the part of its fold that reads nothing of the scene but its settings done
    ahead (`prepare`): its depth denoised, its evidence and SH basis, its colour-solve view resized.
    `Scene.fold` takes it in place of the frame and folds exactly what the frame would fold."""

    frame: Frame
    config: SceneConfig | None = None  # the settings the parts below were made with (None: nothing made)
    front: Prepared | None = None  # the depth front end's result: the frame as it is folded
    evidence: FrameEvidence | None = None
    basis: np.ndarray | None = None  # [M, (sh_degree + 1)^2] SH basis of each observation's view direction
    view: Frame | None = None  # the colour solve's view of the frame, resized (None where it keeps none)

    def nbytes(self) -> int:
        """Bytes of what was made ahead (the evidence, the basis, the view and a denoised depth), which
        a holder of the prepared frame keeps alive besides the frame itself."""
        arrays = [] if self.evidence is None else [v for v in vars(self.evidence).values() if isinstance(v, np.ndarray)]
        arrays += [a for a in (self.basis,) if a is not None]
        if self.view is not None:
            arrays.append(self.view.rgb)
        if self.front is not None and self.front.denoised:
            arrays += [self.front.frame.depth, self.front.frame.depth_std]
        return int(sum(a.nbytes for a in arrays if a is not None))


def prepare(scene: Scene, frame: Frame) -> PreparedFrame:
    """`Scene.prepare`: ``frame`` with the part of its fold that reads nothing of the scene but its
    settings made now (`PreparedFrame`: depth denoising, evidence, the colour solve's view), without
    the scene's lock, so that a caller (the service) overlaps it with the folds of the frames before
    it; ``fold`` of the result folds the same bits as ``fold(frame)``. Made only for a frame with
    sensor depth once the scene's settings are chosen (its first frame), without hole completion
    (which sweeps against the map) and while no learned appearance head weighs the evidence;
    otherwise, or where the frame would be refused (left to the fold, which refuses it in its
    turn), nothing is made. Raises ValueError naming ``frame`` if it is not a Frame."""
    if not isinstance(frame, Frame):
        raise ValueError(f"frame: expected a Frame, got {type(frame).__name__}")
    config = scene.config  # one read: a fold that chooses the settings replaces the object
    if frame.depth is None or not config.chosen or config.depth.completion or not scene.appearance.is_zero:
        return PreparedFrame(frame)
    folded, denoised = denoised_depth(frame, config)
    try:
        evidence, basis = _evidence(folded, config)
    except ValueError:
        return PreparedFrame(frame)
    view = kept_view(frame, config.colour_solve.scale) if config.colour_solve.views else None
    return PreparedFrame(frame, config, Prepared(folded, denoised=denoised), evidence, basis, view)


def _evidence(frame: Frame, config: SceneConfig, appearance=None) -> tuple[FrameEvidence, np.ndarray]:
    """A frame's evidence and each observation's SH basis, [M, (sh_degree + 1)^2]: what `integrate` takes."""
    ev = extract_evidence(frame, config, appearance)
    return ev, observation_sh_basis(ev, frame.camera, config.sh_degree)


def fold_kept(scene: Scene, frame: Frame | PreparedFrame, arrival: int, t0: float) -> FoldReport:
    """`Scene.fold` of ``frame`` (arrival index ``arrival``, started at ``t0``) for a caller that holds
    the scene's lock: the settings the config leaves open chosen (the scene's first frame), the fold
    with its undo record, then the frame kept (with ``keep_frames``) and a checkpoint where one is due."""
    ahead = frame if isinstance(frame, PreparedFrame) else PreparedFrame(frame)
    frame = ahead.frame
    before = None if scene.config.chosen else (scene.config, scene.chosen)
    if before is not None:  # what the settings leave to the first frame is chosen now, once (`choices`)
        _set_config(scene, *choose_settings(scene.config, frame))
    # the fold in progress enters what it overwrites in its undo record, the map's journal; a frame
    # without depth folds the frames that wait for it too, and a refusal of one of those (its labels,
    # the voxel cap) comes after the frame's own integration: the record undoes that
    waiting = frame.depth is None and bool(scene._front.pending)
    record = scene._voxels.journal = _undo_record(scene) if scene._undo.depth or waiting else None
    try:
        report = _fold(scene, ahead, t0)
    except BaseException:
        if waiting:
            _undo_failed_fold(scene, record)
        if before is not None:  # a refused frame chooses nothing
            _set_config(scene, *before)
        raise
    finally:
        scene._voxels.journal = None
        scene._generation += 1
        scene._decoding.forget()
    if record is not None and scene._undo.depth:
        if scene.label_dim != record.label_dim:  # rows were widened: earlier records no longer fit
            scene._undo.clear()
        else:
            scene._undo.push(record, scene._voxels.nbytes())
    if scene._kept is not None:
        scene._arrivals.append(arrival)
        scene._kept.append(frame)
        if scene.checkpoint_every and scene.frames % scene.checkpoint_every == 0:
            scene._checkpoints[scene.frames] = snapshot.encode(scene, *snapshot.snapshot_parts(scene))
    return report


def _undo_failed_fold(scene: Scene, record: FoldUndo) -> None:
    """The state before a fold that failed part way (``record``: its undo record, entered as it went)."""
    undo_folds(scene, [record])
    if scene.label_dim != record.label_dim:  # it widened the rows for its labels: narrowed again
        scene._voxels.set_label_dim(record.label_dim)


def _set_config(scene: Scene, config: SceneConfig, chosen: dict[str, str]) -> None:
    """The settings chosen from the first frame (`choices`), for the scene and the parts that read them."""
    scene.config, scene.chosen = config, chosen
    scene._front.config = scene._decoding.config = config


def _undo_record(scene: Scene) -> FoldUndo:
    """What the next fold may overwrite, but for the voxels' rows and see-through evidence, which
    its integrations add as they go (see `undo`)."""
    return FoldUndo(scene.frames, len(scene._voxels), scene.label_dim, list(scene._front.window.views),
                    list(scene._front.pending), (list(scene._keyframes.indices), scene._keyframes.frames()),
                    (scene._density_sum, scene._density_frames))


def _fold(scene: Scene, ahead: PreparedFrame, t0: float) -> FoldReport:
    frame, index = ahead.frame, scene.frames
    _check_labels(scene, frame)
    points = functools.partial(scene._voxels.representative_points, scene.config.voxel_size)
    # what `prepare` made holds where it was made with the settings the scene folds with now
    made = ahead.config is scene.config and scene.appearance.is_zero
    prepared = ahead.front if made else scene._front.prepare(frame, functools.partial(_check_foldable, scene), points)
    counts = (0, 0, 0, 0) if prepared.pending else _integrate(scene, prepared.frame, (ahead.evidence, ahead.basis) if made else None)
    scene._front.commit(prepared)
    scene._keyframes.add(index, frame, ahead.view if made else None)  # a waiting frame's colours join once a partner arrives
    scene.frames += 1
    also = 0
    if frame.depth is None and not prepared.pending:  # frames that waited for a partner: fold them now, in order
        for waiting in scene._front.ready(points):
            _integrate(scene, waiting)
            also += 1
    gave_nothing = frame.depth is not None and counts[0] == 0
    warnings = depth_warnings(frame.depth, scene.config.range.near, scene.config.range.far) if gave_nothing else []
    if frame.depth is not None:  # the sensor's depth (as folded: denoised or completed), not a sweep's
        warnings += scene._consistency.observe(prepared.frame, scene.config.range.near)
    return FoldReport(index, *counts, ms=(time.perf_counter() - t0) * 1000.0, pending=prepared.pending,
                      also_folded=also, completed_pixels=prepared.completed_pixels, denoised=prepared.denoised,
                      warnings=warnings, sensor=scene.config.sensor.family, sensor_chosen=scene.chosen.get("sensor"))


def _integrate(scene: Scene, frame: Frame, made: tuple[FrameEvidence, np.ndarray] | None = None) -> tuple[int, int, int, int]:
    """Evidence, integration and free space of a frame with depth: (observations, new voxels,
    updated voxels, representative switches); ``made``: its evidence and SH basis, made already."""
    if made is None:
        made = _evidence(frame, scene.config, scene.appearance)
    first_new = len(scene._voxels)
    done = integrate(scene._voxels, *made, scene.config)
    if scene.config.free_space.enabled:
        if scene._voxels.journal is not None:
            scene._voxels.journal.history.append(history_slot(scene._history))
        integrate_free_space(scene._voxels, frame, scene.config, scene._history, first_new)
    if done.touched_voxels:
        scene._density_sum += done.observations / done.touched_voxels
        scene._density_frames += 1
    return done.observations, done.new_voxels, done.touched_voxels - done.new_voxels, done.representative_switches


def _check_foldable(scene: Scene, frame: Frame) -> None:
    """The checks evidence extraction makes that do not need depth (so a waiting frame cannot fail later)."""
    check_client_features(frame, scene.config)
    _check_labels(scene, frame)


def _check_labels(scene: Scene, frame: Frame) -> None:
    """Label channels as the scene's, or as a waiting frame's before the scene has any: a frame that
    set them otherwise would leave the waiting frame to fail, and every frame after it."""
    expected = scene.label_dim or next((f.label_dim for f, _ in scene._front.pending if f.labels is not None), 0)
    if frame.labels is not None and expected and frame.label_dim != expected:
        raise ValueError(f"labels: expected {expected} label channels (as earlier frames), got {frame.label_dim}")


def fold_cost(scene: "Scene", frame: Frame) -> int:
    """Bytes that folding ``frame`` can add to ``scene`` at most, before it folds (no lock needed): a
    fold adds at most one voxel per pixel it lifts (a pixel whose depth lies in the scene's range, or
    any pixel of a frame without depth, whose depth the sweep estimates), each at most
    `VoxelMap.new_voxel_bytes`, and once more in the fold's undo record where the scene keeps them.

    Example:
        >>> from canonical_core import Scene, SceneConfig
        >>> from canonical_core.datasets.synthetic import synthetic_rgbd
        >>> frame = synthetic_rgbd(num_frames=1, width=32, height=24)[0]
        >>> scene = Scene(SceneConfig(voxel_size=0.01))
        >>> before, cost = scene.memory_bytes(), fold_cost(scene, frame)
        >>> _ = scene.fold(frame)
        >>> 0 < scene.memory_bytes() - before <= cost
        True
    """
    if frame.depth is None:
        pixels = frame.width * frame.height
    else:
        near, far = scene.config.range.near, scene.config.range.far
        depth = frame.depth.numpy()  # numpy: one thread, where torch would wake its pool for a count
        pixels = int(np.count_nonzero((depth > near) & (depth < far)))
    per_voxel = scene._voxels.new_voxel_bytes()
    return pixels * (per_voxel * 2 if scene._undo.depth else per_voxel)

