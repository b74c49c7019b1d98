"""Dec: scene fields -> Gaussians (monotone opacity head, analytic initialisation)."""

from .decoder import FOOTPRINT_GAIN, GaussianDecoder, MonotoneOpacity, matrix_to_quaternion

__all__ = ["FOOTPRINT_GAIN", "GaussianDecoder", "MonotoneOpacity", "matrix_to_quaternion"]
