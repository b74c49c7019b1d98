"""Real data: a scene fused from shelf frames, rendered back at one of its input cameras."""

from __future__ import annotations

import pytest
import torch

from canonical_core.datasets import load_tsdf_fusion
from canonical_core.rendering import render
from canonical_core.scene import Scene, SceneConfig

pytestmark = pytest.mark.realdata

VOXEL_SIZE = 0.004


def psnr(rendered: torch.Tensor, target: torch.Tensor) -> float:
    return float(10 * torch.log10(1 / ((rendered - target) ** 2).mean()))


@pytest.mark.slow
def test_fused_shelf_renders_its_input_view(shelf_dir):
    frames = load_tsdf_fusion(shelf_dir)
    scene = Scene(SceneConfig(voxel_size=VOXEL_SIZE))
    for index in range(0, len(frames), 8):  # 7 of the 50 frames, spanning the sweep
        scene.fold(frames[index])
    view = frames[24]
    result = render(scene.decode(), view.camera, ("rgb", "depth", "alpha"))

    image = view.rgb.float() / 255
    covered = result.alpha > 0.5
    sensor = view.depth
    measured = covered & (sensor > 0)
    depth_error = (result.depth - sensor).abs()[measured].median().item()
    # Measured (decoder at its analytic init): coverage 0.86, PSNR 12.5 dB over all pixels and
    # 17.9 dB over covered ones (DESIGN.md: fused scenes reach 15-19 dB covered; uncovered pixels
    # stay black), median depth error 2.5 mm. The floors sit ~1 dB below and the depth bound is
    # one voxel, leaving room for fold/decoder changes, while a broken camera still fails: w2c
    # passed as c2w measured 8.9 dB covered and 69 mm, another frame's camera 10.3 dB and 30 mm.
    assert covered.float().mean() > 0.8
    assert psnr(result.rgb, image) > 11.5
    assert psnr(result.rgb[covered], image[covered]) > 16.5
    assert depth_error < VOXEL_SIZE
