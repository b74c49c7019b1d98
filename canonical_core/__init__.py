"""CanonicalGS Fusion core: posed frames -> reliability-guided sparse voxel scene -> 3D Gaussians.

No web imports here: ``import canonical_core`` works in a notebook without FastAPI.

Example:
    >>> import canonical_core as cc
    >>> scene = cc.Scene(cc.SceneConfig(voxel_size=0.01))
    >>> len(scene.decode())
    0
"""

import os

# Idle OpenMP threads (torch's and numba's, two teams of a thread a core) sleep instead of spinning:
# where anything else takes a core, spinning threads take turns with the threads that have work,
# and every parallel kernel waits for its slowest thread. OpenMP reads this once, when torch or
# numba loads it, so it is set before they load; an environment that sets it keeps its own.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .camera import Camera  # noqa: E402
from .evidence import estimate_depth  # noqa: E402
from .frame import Frame  # noqa: E402
from .gaussians import Gaussians, load_ply, load_splat, save_ply, save_splat  # noqa: E402
from .rendering import RenderResult, render  # noqa: E402
from .scene import CapacityError, FoldReport, Scene, SceneConfig, aggregate_batch  # noqa: E402

__all__ = [
    "Camera", "CapacityError", "FoldReport", "Frame", "Gaussians", "RenderResult", "Scene", "SceneConfig",
    "aggregate_batch", "estimate_depth", "load_ply", "load_splat", "render", "save_ply", "save_splat",
]
