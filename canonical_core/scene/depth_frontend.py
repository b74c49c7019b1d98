"""The depth front end: everything that turns an incoming frame into a frame with depth and a
depth std, before its evidence is extracted and integrated.

- Sensor depth far rougher than its noise model is replaced by its local median (`evidence.denoise`).
- With ``depth.completion``, the large holes of sensor depth are filled by a plane sweep against
  recent views (`evidence.complete_depth`; only the holes are swept).
- A frame without depth gets it from a plane sweep against recent views, its U_pos becoming its
  depth std. While no earlier view overlaps it, it waits (pending) and is swept once a later frame
  gives it a partner.

It keeps the source window (`evidence.SourceWindow`: cameras and matching features of recent
views, never images) and the pending frames. The swept depth range comes from the points the
scene already holds, which the caller passes as a function (`VoxelMap.representative_points`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import torch

from ..camera import Camera
from ..evidence import (SourceView, SourceWindow, complete_depth, denoise_rough_depth, depth_range_from_points,
                        estimate_depth, sensor_depth_std, sensor_holes)
from ..frame import Frame, check_rgb_only
from ..config import SceneConfig
from .keyframes import view_from_arrays, view_to_arrays

Points = Callable[[], "np.ndarray | None"]  # the scene's points ([N, 3]), None while it holds none


@dataclass(frozen=True)
class Prepared:
    """A frame on its way to integration (`DepthFrontEnd.prepare`).

    ``frame`` has depth unless ``pending`` (then it waits for a partner and is not integrated now).
    ``view`` is its source view, which `DepthFrontEnd.commit` adds to the window once the frame is
    integrated (None: the frame does not join the window); ``view_depth`` sets that view's typical
    depth (None: its own).
    """

    frame: Frame
    view: SourceView | None = None
    pending: bool = False
    view_depth: torch.Tensor | None = None  # [H, W] metres
    completed_pixels: int = 0
    denoised: bool = False


def denoised_depth(frame: Frame, config: SceneConfig) -> tuple[Frame, bool]:
    """``frame`` (with depth) with its depth replaced by the local median where it is far rougher
    than its noise model (`evidence.denoise`), and whether it was."""
    c = config
    depth = frame.depth.numpy()
    std = None if frame.depth_std is None else frame.depth_std.numpy()
    smooth, smooth_std = denoise_rough_depth(depth, std, c.depth.denoise_radius, c.sensor.sigma0, c.sensor.sigma2,
                                             c.sensor.sigma_ref)
    if smooth is depth:
        return frame, False
    return dataclasses.replace(frame, depth=torch.from_numpy(smooth), depth_std=torch.from_numpy(smooth_std)), True


class DepthFrontEnd:
    """Depth for each incoming frame (see the module), with the source window and pending frames."""

    def __init__(self, config: SceneConfig):
        self.config = config
        self.window = SourceWindow(config.depth.source_window)
        # frames without depth that wait for a partner, with their window view (None after loading
        # a snapshot: recomputed when the frame is swept)
        self.pending: list[tuple[Frame, SourceView | None]] = []

    def prepare(self, frame: Frame, check: Callable[[Frame], None], points: Points) -> Prepared:
        """``frame`` made ready to integrate. ``check`` raises ValueError for a frame the scene could
        not integrate; it runs before any sweep (and before a frame is kept waiting). Changes nothing."""
        if frame.depth is None:
            return self._without_depth(frame, check, points)
        frame, denoised = denoised_depth(frame, self.config)
        view, completed = None, 0
        if self.config.depth.completion:
            check(frame)  # before the sweep's cost
            view = self.window.view_of(frame)
            sources = self._sources_for(frame.camera)
            if sources:
                frame, completed = self._completed(frame, sources, view, points)
        return Prepared(frame, view, completed_pixels=completed, denoised=denoised)

    def commit(self, prepared: Prepared) -> None:
        """After ``prepared`` was integrated (or accepted as pending): its view joins the window, a
        pending frame the waiting list. A frame that fails to integrate leaves both as they were."""
        if prepared.view is not None:
            self.window.add(prepared.view, depth=prepared.view_depth)
        if prepared.pending:
            self.pending.append((prepared.frame, prepared.view))

    def ready(self, points: Points) -> Iterator[Frame]:
        """The waiting frames that now have a source view, in arrival order, each with its swept
        depth. A frame leaves the waiting list when the caller asks for the next one (it was
        integrated); if integration raises, it stays."""
        for entry in list(self.pending):
            waiting, view = entry
            sources = self._sources_for(waiting.camera)
            if sources:
                yield self._with_estimated_depth(waiting, sources, view, points)
                self.pending.remove(entry)

    # -- the stages ---------------------------------------------------------------------------
    def _without_depth(self, frame: Frame, check: Callable[[Frame], None], points: Points) -> Prepared:
        check(frame)
        check_rgb_only(frame)
        sources = self._sources_for(frame.camera)
        if not sources and len(self.pending) >= self.config.depth.source_window:
            raise ValueError(f"depth: the frame has no depth and no earlier view overlaps it, and "
                             f"{len(self.pending)} frames already wait for a partner")
        view = self.window.view_of(frame)  # matching features once: the sweep's reference and the window's view
        if not sources:
            return Prepared(frame, view, pending=True)
        estimated = self._with_estimated_depth(frame, sources, view, points)
        return Prepared(estimated, view, view_depth=estimated.depth)

    def _sources_for(self, camera: Camera) -> list[SourceView]:
        """Source views for a sweep at ``camera`` (never its own view: selection needs a baseline)."""
        return self.window.select(camera, k=self.config.depth.sources)

    def _with_estimated_depth(self, frame: Frame, sources: list[SourceView], view: SourceView | None,
                              points: Points, where: np.ndarray | None = None) -> Frame:
        """``frame`` with the swept depth (and its U_pos as depth std); only at ``where`` if given."""
        held = points()
        near_far = None if held is None else depth_range_from_points(frame.camera, held)
        near, far = near_far if near_far is not None else (None, None)
        depth, std = estimate_depth(frame, sources, near=near, far=far, num_hypotheses=self.config.depth.hypotheses,
                                    reference=view, where=where)
        return dataclasses.replace(frame, depth=torch.from_numpy(depth), depth_std=torch.from_numpy(std))

    def _completed(self, frame: Frame, sources: list[SourceView], view: SourceView, points: Points) -> tuple[Frame, int]:
        """``frame`` with the large holes of its depth filled by the sweep (`complete_depth`), and
        the number of pixels filled."""
        c = self.config
        holes = sensor_holes(frame.depth.numpy(), c.depth.completion_radius)
        if not holes.any():
            return frame, 0
        swept = self._with_estimated_depth(frame, sources, view, points, where=holes)  # only the holes are swept
        std = frame.depth_std if frame.depth_std is not None else sensor_depth_std(
            frame.depth, c.sensor.sigma0, c.sensor.sigma2, c.sensor.sigma_ref)
        depth, std, filled = complete_depth(frame.depth.numpy(), std.numpy(), swept.depth.numpy(),
                                            swept.depth_std.numpy(), holes)
        if not filled.any():  # the frame as it came: its evidence is then bit-identical to a plain fold
            return frame, 0
        return dataclasses.replace(frame, depth=torch.from_numpy(depth), depth_std=torch.from_numpy(std)), int(filled.sum())

    # -- snapshot -----------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The window (``window.*``) and the waiting frames (``pending.<i>.*``) as snapshot arrays."""
        arrays = {f"window.{k}": v for k, v in self.window.to_arrays().items()}
        for i, (f, _) in enumerate(self.pending):
            arrays |= view_to_arrays(f"pending.{i}", f)
            arrays |= {f"pending.{i}.{name}": getattr(f, name).numpy() for name in ("features", "labels")
                       if getattr(f, name) is not None}
            if f.num_classes is not None:  # labels as a class map
                arrays[f"pending.{i}.num_classes"] = np.array(f.num_classes, np.int64)
        return arrays

    def load_arrays(self, arrays, pending: int) -> None:
        """Restore what `to_arrays` wrote (``arrays``: a mapping such as an open npz) with ``pending`` frames."""
        self.window = SourceWindow.from_arrays({k[len("window."):]: arrays[k] for k in arrays.files
                                                if k.startswith("window.")})
        for i in range(pending):
            extra = {name: arrays[f"pending.{i}.{name}"].copy() if f"pending.{i}.{name}" in arrays.files else None
                     for name in ("features", "labels")}
            if f"pending.{i}.num_classes" in arrays.files:
                extra["num_classes"] = int(arrays[f"pending.{i}.num_classes"])
            self.pending.append((view_from_arrays(f"pending.{i}", arrays, **extra), None))
