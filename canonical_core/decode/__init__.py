"""Dec: scene fields -> Gaussians (monotone opacity head, analytic initialisation), and the
render-consistent colour solve against the input views."""

from .colour_solve import SolveStopped, colour_offsets, colour_system, solve_colours, with_colour_offsets
from .eigen import symmetric_eigh3, symmetric_eigh3_reference
from .decoder import FOOTPRINT_GAIN, FULL_VOXEL_EXTENT, GaussianDecoder, MonotoneOpacity, matrix_to_quaternion, support_unit

__all__ = [
    "FOOTPRINT_GAIN", "FULL_VOXEL_EXTENT", "GaussianDecoder", "MonotoneOpacity", "SolveStopped", "colour_offsets", "colour_system",
    "matrix_to_quaternion", "solve_colours", "support_unit", "symmetric_eigh3", "symmetric_eigh3_reference",
    "with_colour_offsets",
]
