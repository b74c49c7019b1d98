"""The CUDA backend (gsplat) against the CPU fast path. Skipped without CUDA and gsplat."""

from __future__ import annotations

import pytest
import torch

from canonical_core.rendering import render

from .scenes import look_at_camera, random_scene

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]
ALL_OUTPUTS = ("rgb", "depth", "alpha", "features", "labels")


def test_gsplat_agrees_with_the_cpu_fast_path():
    pytest.importorskip("gsplat")
    gaussians = random_scene(2000, 21, sh_degree=3, scale_range=(0.01, 0.08), opacity_range=(0.3, 1.0))
    camera = look_at_camera(96, 72, 80.0, [0.4, -0.3, -3.0], [0.0, 0.0, 0.0], roll=0.2)
    cpu = render(gaussians, camera, ALL_OUTPUTS, background=(0.1, 0.2, 0.3), backend="cpu")
    gpu = render(gaussians.to("cuda"), camera, ALL_OUTPUTS, background=(0.1, 0.2, 0.3), backend="auto")
    assert gpu.rgb.is_cuda and gpu.labels.dtype == torch.int64
    # gsplat truncates splats by its own screen radius, not the 3-sigma ellipse: the images agree
    # closely on average, not to the last bit at splat edges.
    for name in ("rgb", "alpha", "features"):
        difference = (getattr(gpu, name).cpu() - getattr(cpu, name)).abs().mean().item()
        assert difference < 5e-3, f"{name}: mean |gsplat - cpu| = {difference:.3g}"
    both = (gpu.alpha.cpu() > 0.5) & (cpu.alpha > 0.5)
    assert (gpu.depth.cpu() - cpu.depth)[both].abs().median() < 1e-3


def test_gsplat_backend_is_differentiable():
    pytest.importorskip("gsplat")
    gaussians = random_scene(200, 22).to("cuda")
    gaussians.means.requires_grad_()
    camera = look_at_camera(48, 48, 40.0, [0.0, 0.0, -3.0], [0.0, 0.0, 0.0])
    result = render(gaussians, camera, ("rgb", "depth", "alpha"), backend="gsplat")
    (result.rgb.sum() + result.depth.sum()).backward()
    assert gaussians.means.grad is not None and torch.isfinite(gaussians.means.grad).all()
    assert gaussians.means.grad.abs().sum() > 0


def test_median_depth_on_cuda_tensors_comes_from_the_cpu_backend():
    pytest.importorskip("gsplat")
    gaussians = random_scene(500, 23, scale_range=(0.02, 0.1), opacity_range=(0.3, 1.0))
    camera = look_at_camera(48, 40, 40.0, [0.2, 0.1, -3.0], [0.0, 0.0, 0.0])
    cpu = render(gaussians, camera, ("depth", "alpha"), depth_mode="median", backend="cpu")
    gpu = render(gaussians.to("cuda"), camera, ("depth", "alpha"), depth_mode="median", backend="auto")
    assert gpu.depth.is_cuda and torch.equal(gpu.depth.cpu(), cpu.depth)
    with pytest.raises(ValueError, match="^depth_mode: 'median' is computed by the cpu and reference backends"):
        render(gaussians.to("cuda"), camera, ("depth",), depth_mode="median", backend="gsplat")
