"""CanonicalGS Fusion core: posed frames -> reliability-guided sparse voxel scene -> 3D Gaussians.

No web imports here: ``import canonical_core`` works in a notebook without FastAPI.
"""

from .camera import Camera
from .frame import Frame
from .gaussians import Gaussians, load_ply, load_splat, save_ply, save_splat
from .scene.config import SceneConfig

__all__ = ["Camera", "Frame", "Gaussians", "SceneConfig", "load_ply", "load_splat", "save_ply", "save_splat"]
