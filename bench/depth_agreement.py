"""Why held-out depth agreement and covered PSNR change with N: floaters, or a different mix of pixels.

    python bench/depth_agreement.py ../shared/data/hololens_office [--methods canonical,open3d_tsdf] [--scale 1]

The evaluation's depth agreement is the share of *covered* pixels (with held-out sensor depth) whose
rendered depth is within 2 voxels of the sensor's. Covered pixels grow with N, so the figure can fall
because new, harder pixels join (far walls, grazing floor), not because the scene got worse. Per
method and N (the evaluation's protocol and scoring), this prints:

- ``agree``: the evaluation's figure;
- ``agree@N=2 pixels``: the same measure on the pixels the method covered at the smallest N only (a
  fixed pixel set: a fall here means the scene got worse where it was already drawn);
- ``in front`` / ``behind``: shares of the covered pixels whose rendered depth is more than 2 voxels
  in front of the sensor's (floaters, or foreground colour spilling past its edge) or behind it
  (see-through surfaces, holes the render looks past);
- ``PSNR covered`` and ``PSNR@N=2 pixels``: the evaluation's covered PSNR (each N on the pixels it
  covers), and the PSNR on the pixels the smallest N covered (those of them still covered): whether
  colour got worse where the scene was already drawn, or the newly drawn pixels are harder.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import build, check_methods  # noqa: E402
from canonical_core.eval.metrics import DEPTH_TOLERANCE_VOXELS, covered, psnr  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import default_voxel_size  # noqa: E402
from canonical_core.eval.tuning import allowed_views  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402


def share(mask: torch.Tensor, of: torch.Tensor) -> float:
    return float(mask[of].double().mean()) if bool(of.any()) else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data")
    parser.add_argument("--methods", default="canonical,pixel_aligned")
    parser.add_argument("--views", default="2,4,8,16")
    parser.add_argument("--scale", type=float, default=1.0)
    args = parser.parse_args()
    methods = check_methods(args.methods.split(","))
    sequence = load_dataset(args.data)
    views = allowed_views(len(sequence), tuple(int(v) for v in args.views.split(",")))
    split = interpolation_split(len(sequence), views)
    frames = {p: resize_frame(sequence[p], args.scale) for p in sorted(set(split.heldout).union(*split.inputs.values()))}
    targets = [frames[p] for p in split.heldout]
    voxel = default_voxel_size([frames[p] for p in split.inputs[max(views)]])
    tol = DEPTH_TOLERANCE_VOXELS * voxel
    print(machine_summary())
    print(f"{sequence.name}: voxel {voxel:g}, tolerance {tol:g}, N = {list(views)}\n")
    rows = []
    for name in methods:
        first: list[torch.Tensor] = []
        first_drawn: list[torch.Tensor] = []
        for n_views in views:
            model, _ = build(name, [frames[p] for p in split.inputs[n_views]], voxel)
            counts = {"agree": [], "fixed": [], "front": [], "behind": [], "coverage": [], "psnr": [], "psnr_fixed": []}
            for i, target in enumerate(targets):
                view = model.render(target.camera)
                has = target.depth > 0
                drawn = covered(view.alpha)
                mask = drawn & has
                if n_views == views[0]:
                    first.append(mask)
                    first_drawn.append(drawn)
                truth = target.rgb.float() / 255.0
                counts["psnr"].append(psnr(view.rgb, truth, drawn))
                counts["psnr_fixed"].append(psnr(view.rgb, truth, drawn & first_drawn[i]))
                err = view.depth - target.depth
                counts["agree"].append(share(err.abs() <= tol, mask))
                counts["fixed"].append(share(err.abs() <= tol, first[i] & mask))
                counts["front"].append(share(err < -tol, mask))
                counts["behind"].append(share(err > tol, mask))
                counts["coverage"].append(float(mask.double().mean()))
            mean = {k: float(torch.tensor(v).nanmean()) for k, v in counts.items()}
            rows.append({"method": name, "N": n_views, "covered with depth": f"{mean['coverage']:.3f}",
                         "agree": f"{mean['agree']:.3f}", "agree@N=2 pixels": f"{mean['fixed']:.3f}",
                         "in front": f"{mean['front']:.3f}", "behind": f"{mean['behind']:.3f}",
                         "PSNR covered": f"{mean['psnr']:.2f}", "PSNR@N=2 pixels": f"{mean['psnr_fixed']:.2f}"})
    print_table(f"Held-out depth agreement and covered PSNR, {sequence.name}", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
