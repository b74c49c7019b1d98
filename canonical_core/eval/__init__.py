"""Evaluation: metrics, protocols, methods and baselines, the report (the classical peer lives in `open3d_tsdf`).

``evaluate`` (in `run`) runs the whole protocol on a dataset; ``canonical eval`` / ``python -m
canonical_core.eval`` is its command line (`cli`).
"""

from .methods import METHODS, Method, View, build
from .metrics import coverage, psnr, ssim
from .protocol import Split, extrapolation_split, interpolation_split
from .run import evaluate

__all__ = ["METHODS", "Method", "Split", "View", "build", "coverage", "evaluate", "extrapolation_split",
           "interpolation_split", "psnr", "ssim"]
