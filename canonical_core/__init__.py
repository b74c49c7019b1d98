"""CanonicalGS Fusion core: posed frames -> reliability-guided sparse voxel scene -> 3D Gaussians.

No web imports here: ``import canonical_core`` works in a notebook without FastAPI.

Example:
    >>> import canonical_core as cc
    >>> scene = cc.Scene(cc.SceneConfig(voxel_size=0.01))
    >>> len(scene.decode())
    0
"""

from .camera import Camera
from .evidence import estimate_depth
from .frame import Frame
from .gaussians import Gaussians, load_ply, load_splat, save_ply, save_splat
from .rendering import RenderResult, render
from .scene import CapacityError, FoldReport, Scene, SceneConfig, aggregate_batch

__all__ = [
    "Camera", "CapacityError", "FoldReport", "Frame", "Gaussians", "RenderResult", "Scene", "SceneConfig",
    "aggregate_batch", "estimate_depth", "load_ply", "load_splat", "render", "save_ply", "save_splat",
]
