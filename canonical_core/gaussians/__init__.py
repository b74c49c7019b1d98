"""Gaussian primitives: the container and its PLY / .splat formats."""

from .container import SH_C0, Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from .io import load_ply, load_splat, ply_bytes, save_ply, save_splat, splat_bytes

__all__ = ["SH_C0", "Gaussians", "rgb_to_sh_dc", "sh_dc_to_rgb", "load_ply", "load_splat", "ply_bytes", "save_ply", "save_splat", "splat_bytes"]
