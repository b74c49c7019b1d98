"""How much held-out covered PSNR the representation can give at all: the fidelity ceiling.

    python bench/ceiling.py [--data ../shared/data/realsense_shelf] [--views 16] [--voxels 0.004,0.002]

Per voxel size, with the evaluation's protocol and scoring (`canonical_core.eval`):
- "self": every held-out frame fused *alone* and rendered at its own pose. Nothing is interpolated and
  nothing is misregistered, so this is what one Gaussian per voxel can reproduce of a captured image
  (colour averaged over a voxel's footprint, sensor holes).
- "self, alpha-normalised": the same, with the renders divided by their alpha on covered pixels. One
  view's support leaves alpha at about 0.9, so this is the fair ceiling for a scene of many views,
  whose covered alpha is near 1.
- "N views": the held-out frames rendered from the scene of N input views (the evaluation's number).
- "N views, alpha-normalised": the same renders divided by their alpha on covered pixels, i.e. the
  score if every covered surface were fully opaque (what opacity costs on covered pixels).
A covered-PSNR target stated against a peer (such as Open3D's figure + 2 dB) is reachable only if
it is below the alpha-normalised self row: compare the two.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import build  # noqa: E402
from canonical_core.eval.metrics import covered, psnr  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import score  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def alpha_normalised_covered_psnr(model, targets) -> float:
    """Mean covered PSNR of the renders divided by their alpha (covered pixels only)."""
    values = []
    for frame in targets:
        view = model.render(frame.camera)
        mask = covered(view.alpha)
        rgb = (view.rgb / view.alpha[..., None].clamp_min(1e-6)).clamp(0.0, 1.0)
        values.append(psnr(rgb, frame.rgb.float() / 255.0, mask))
    return float(np.mean(values))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", type=int, default=16)
    p.add_argument("--voxels", default="0.004,0.002", help="comma-separated voxel sizes in metres")
    args = p.parse_args(argv)
    frames = load_dataset(args.data)
    split = interpolation_split(len(frames), [args.views])
    targets = [frames[i] for i in split.heldout]
    print(machine_summary())
    rows = []
    for voxel in (float(v) for v in args.voxels.split(",")):
        alone = [(build("canonical", [t], voxel)[0], t) for t in targets]
        metrics = [score(model, [t], voxel).metrics for model, t in alone]
        rows.append({"voxel mm": f"{voxel * 1000:g}", "scene": "self (each held-out frame alone)",
                     "PSNR dB": f"{np.mean([m['psnr'] for m in metrics]):.2f}",
                     "covered PSNR dB": f"{np.mean([m['psnr_covered'] for m in metrics]):.2f}",
                     "coverage": f"{np.mean([m['coverage'] for m in metrics]):.3f}", "Gaussians": "-"})
        rows.append({"voxel mm": f"{voxel * 1000:g}", "scene": "self, alpha-normalised", "PSNR dB": "-",
                     "covered PSNR dB": f"{np.mean([alpha_normalised_covered_psnr(m, [t]) for m, t in alone]):.2f}",
                     "coverage": "-", "Gaussians": "-"})
        model, _ = build("canonical", [frames[i] for i in split.inputs[args.views]], voxel)
        metrics = score(model, targets, voxel).metrics
        rows.append({"voxel mm": f"{voxel * 1000:g}", "scene": f"{args.views} views",
                     "PSNR dB": f"{metrics['psnr']:.2f}", "covered PSNR dB": f"{metrics['psnr_covered']:.2f}",
                     "coverage": f"{metrics['coverage']:.3f}", "Gaussians": f"{metrics['gaussians']:,}"})
        rows.append({"voxel mm": f"{voxel * 1000:g}", "scene": f"{args.views} views, alpha-normalised",
                     "PSNR dB": "-", "covered PSNR dB": f"{alpha_normalised_covered_psnr(model, targets):.2f}",
                     "coverage": "-", "Gaussians": "-"})
        print(f"voxel {voxel * 1000:g} mm done", file=sys.stderr, flush=True)
    print_table(f"fidelity ceiling: {len(targets)} held-out frames {list(split.heldout)}, "
                f"{targets[0].width}x{targets[0].height}", rows)


if __name__ == "__main__":
    main()
