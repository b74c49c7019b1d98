"""Gaussian primitives: the container and its PLY / .splat formats."""

from .container import SH_C0, Gaussians, rgb_to_sh_dc, sh_dc_to_rgb
from .io import ENCODE_ROWS, Encoded, load_ply, load_splat, ply_bytes, ply_file, save_ply, save_splat, splat_bytes, splat_file

__all__ = ["ENCODE_ROWS", "SH_C0", "Encoded", "Gaussians", "rgb_to_sh_dc", "sh_dc_to_rgb", "load_ply", "load_splat", "ply_bytes", "ply_file",
           "save_ply", "save_splat", "splat_bytes", "splat_file"]
