"""Dec: scene fields -> Gaussians (monotone opacity head, analytic initialisation)."""

from .decoder import FOOTPRINT_GAIN, FULL_VOXEL_EXTENT, GaussianDecoder, MonotoneOpacity, matrix_to_quaternion, support_unit

__all__ = ["FOOTPRINT_GAIN", "FULL_VOXEL_EXTENT", "GaussianDecoder", "MonotoneOpacity", "matrix_to_quaternion", "support_unit"]
