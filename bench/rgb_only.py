"""Fusion from RGB only (plane-sweep depth) vs RGB-D on the same frames, and reliability vs uniform.

    python bench/rgb_only.py [--data ../shared/data/realsense_shelf] [--views 8] [--scale 0.5]

Input views round(linspace(0, n - 1, N)); held-out frames 2, 6, 12, 17, 22, 27, 32, 37, 41, 47 (the
evaluation protocol's set for n = 50); frames downscaled by ``scale`` (depth by nearest sampling).
Prints all-pixel and covered PSNR (alpha >= 0.5) on the held-out frames for each setting.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

import canonical_core as cc  # noqa: E402
from canonical_core import Frame  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"
HELD_OUT = [2, 6, 12, 17, 22, 27, 32, 37, 41, 47]


def resized(frame: Frame, step: int, with_depth: bool) -> Frame:
    return Frame(rgb=frame.rgb[::step, ::step].contiguous(), camera=frame.camera.scaled(1.0 / step),
                 depth=frame.depth[::step, ::step].contiguous() if with_depth else None, frame_id=frame.frame_id)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--step", type=int, default=2, help="keep every step-th pixel (2: 640x480 -> 320x240)")
    p.add_argument("--voxel", type=float, default=0.008)
    args = p.parse_args(argv)
    frames = load_dataset(args.data)
    inputs = [int(i) for i in np.linspace(0, len(frames) - 1, args.views).round()]
    held = [h for h in HELD_OUT if h < len(frames) and h not in inputs]
    print(machine_summary())
    rows = []
    for label, with_depth, weighting in (("RGB-D", True, "full"), ("RGB only", False, "full"),
                                         ("RGB-D, no_reliability", True, "no_reliability"),
                                         ("RGB only, no_reliability", False, "no_reliability")):
        scene = cc.Scene(cc.SceneConfig(voxel_size=args.voxel, weighting=weighting))
        for i in inputs:
            scene.fold(resized(frames[i], args.step, with_depth))
        g = scene.decode()
        psnr, covered = [], []
        for h in held:
            f = resized(frames[h], args.step, True)
            out = cc.render(g, f.camera)
            err = (out.rgb - f.rgb.float() / 255) ** 2
            psnr.append(-10 * np.log10(err.mean().item()))
            covered.append(-10 * np.log10(err[out.alpha > 0.5].mean().item()))
        rows.append({"input": label, "PSNR dB": f"{np.mean(psnr):.2f}", "covered PSNR dB": f"{np.mean(covered):.2f}",
                     "Gaussians": f"{len(g):,}"})
    size = f"{frames[0].width // args.step}x{frames[0].height // args.step}"
    print_table(f"{args.views} input views, {len(held)} held-out frames, {size}, {args.voxel * 1000:g} mm voxels", rows)


if __name__ == "__main__":
    main()
