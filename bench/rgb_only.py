"""Fusion from RGB only (plane-sweep depth) vs RGB-D on the same frames, and reliability vs uniform.

    python bench/rgb_only.py [--data ../shared/data/realsense_shelf] [--views 8] [--scale 0.5] [--voxel 0.008]

The evaluation's protocol and scoring (`canonical_core.eval`): inputs and held-out frames from
`interpolation_split` for N = ``views``, frames resized by `resize_frame` (colour area-averaged,
depth nearest), all-pixel and covered PSNR from `score`. RGB-only inputs are the same frames with
their depth removed; held-out frames keep theirs (the score's depth agreement uses it).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

import canonical_core as cc  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import SplatModel  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import score  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--scale", type=float, default=0.5, help="image scale (0.5: 640x480 -> 320x240)")
    p.add_argument("--voxel", type=float, default=0.008)
    args = p.parse_args(argv)
    frames = load_dataset(args.data)
    split = interpolation_split(len(frames), [args.views])
    rgbd = [resize_frame(frames[i], args.scale) for i in split.inputs[args.views]]
    rgb_only = [dataclasses.replace(f, depth=None, depth_std=None) for f in rgbd]
    targets = [resize_frame(frames[i], args.scale) for i in split.heldout]
    print(machine_summary())
    rows = []
    for label, inputs, weighting in (("RGB-D", rgbd, "full"), ("RGB only", rgb_only, "full"),
                                     ("RGB-D, no_reliability", rgbd, "no_reliability"),
                                     ("RGB only, no_reliability", rgb_only, "no_reliability")):
        scene = cc.Scene(cc.SceneConfig(voxel_size=args.voxel, weighting=weighting))
        for frame in inputs:
            scene.fold(frame)
        metrics, _ = score(SplatModel(scene.decode()), targets, args.voxel)
        rows.append({"input": label, "PSNR dB": f"{metrics['psnr']:.2f}",
                     "covered PSNR dB": f"{metrics['psnr_covered']:.2f}", "Gaussians": f"{metrics['gaussians']:,}"})
    size = f"{targets[0].width}x{targets[0].height}"
    print_table(f"{args.views} input views, {len(targets)} held-out frames {list(split.heldout)}, {size}, "
                f"{args.voxel * 1000:g} mm voxels", rows)


if __name__ == "__main__":
    main()
