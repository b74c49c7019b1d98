"""Rendering: ``render(gaussians, camera, ...)`` with a PyTorch reference, a fast CPU path (numba + C) and gsplat on CUDA."""

from .renderer import Backend, Colour, DepthMode, Output, RenderResult, render

__all__ = ["Backend", "Colour", "DepthMode", "Output", "RenderResult", "render"]
