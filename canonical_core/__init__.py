"""CanonicalGS Fusion core: posed frames -> reliability-guided sparse voxel scene -> 3D Gaussians.

No web imports here: ``import canonical_core`` works in a notebook without FastAPI.

Example:
    >>> import canonical_core as cc
    >>> scene = cc.Scene(cc.SceneConfig(voxel_size=0.01))
    >>> len(scene.decode())
    0
"""

import importlib
import os
from typing import TYPE_CHECKING

# Idle OpenMP threads (torch's and numba's, two teams of a thread a core) sleep instead of spinning:
# where anything else takes a core, spinning threads take turns with the threads that have work,
# and every parallel kernel waits for its slowest thread. OpenMP reads this once, when torch or
# numba loads it, so it is set before they load; an environment that sets it keeps its own.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numba's parallel kernels run on OpenMP's team, the one that policy and the thread counts tune (and
# the one the figures in docs/performance.md were measured on); numba's own order tries Intel TBB
# first, so a machine with TBB installed would run them on another pool (and an old TBB, such as
# Open3D's wheel carries, prints a warning on every process). Set before numba loads, as above.
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", "omp tbb workqueue")

# The facade's names load on first use (PEP 562): ``import canonical_core.datasets`` to list a capture,
# or ``canonical_core.config`` to read settings, does not load torch and the method with them.
_EXPORTS = {
    "Camera": "camera", "CapacityError": "scene", "FoldReport": "scene", "Frame": "frame", "Gaussians": "gaussians",
    "RenderResult": "rendering", "Scene": "scene", "SceneConfig": "scene", "aggregate_batch": "scene",
    "estimate_depth": "evidence", "load_ply": "gaussians", "load_splat": "gaussians", "render": "rendering",
    "save_ply": "gaussians", "save_splat": "gaussians",
}
__all__ = sorted(_EXPORTS)

if TYPE_CHECKING:  # what type checkers and editors see: the same names, imported at once
    from .camera import Camera
    from .evidence import estimate_depth
    from .frame import Frame
    from .gaussians import Gaussians, load_ply, load_splat, save_ply, save_splat
    from .rendering import RenderResult, render
    from .scene import CapacityError, FoldReport, Scene, SceneConfig, aggregate_batch


def __getattr__(name: str):
    """A facade name, imported from its module; else a submodule (``canonical_core.scene`` after a bare
    ``import canonical_core``, as when the facade imported them all at once)."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    else:
        try:
            value = importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":  # the submodule exists; something it imports does not
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    globals()[name] = value  # found directly from now on
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
