"""Which input frame costs held-out quality: the N-view scene scored with each input left out in turn.

    python bench/leave_one_out.py ../shared/data/hololens_office [--n 8] [--method canonical] [--scale 1]

For the evaluation's split (inputs ``round(linspace(0, n - 1, N))``, its held-out frames, its voxel
size and its scoring), this prints:

- the covered PSNR at each held-out frame (and their mean) of the scene fused from all N inputs, and
  of the scene fused from the inputs without each one in turn: a frame whose removal raises a held-out
  frame's PSNR costs that frame quality (a surface only it sees drawn in front of, or through, what the
  held-out frame shows; or a pose, depth or colour that disagrees with the others);
- the inputs' pairwise depth agreement: the share of frame i's depth, lifted with its pose and
  projected into frame j, that lands within 2 voxels of j's own depth where j has depth (occlusion
  lowers it too: read it across pairs of similar overlap).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import build, check_methods  # noqa: E402
from canonical_core.eval.metrics import DEPTH_TOLERANCE_VOXELS, covered, psnr  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import default_voxel_size  # noqa: E402
from canonical_core.eval.tuning import allowed_views  # noqa: E402
from canonical_core.frame import Frame, resize_frame  # noqa: E402


def held_out_psnr(method: str, inputs: list[Frame], targets: list[Frame], voxel: float) -> list[float]:
    model, _ = build(method, inputs, voxel)
    scores = []
    for target in targets:
        view = model.render(target.camera)
        scores.append(psnr(view.rgb, target.rgb.float() / 255.0, covered(view.alpha)))
    return scores


def depth_agreement(src: Frame, dst: Frame, tolerance: float) -> float:
    """Share of src's depth, lifted and projected into dst, within ``tolerance`` of dst's depth there."""
    v, u = torch.nonzero(src.depth > 0, as_tuple=True)
    uv, z = dst.camera.project(src.camera.lift(torch.stack([u, v], -1).float(), src.depth[v, u]))
    ui, vi = uv[:, 0].round().long(), uv[:, 1].round().long()
    inside = (z > 0) & (ui >= 0) & (ui < dst.width) & (vi >= 0) & (vi < dst.height)
    observed = dst.depth[vi[inside], ui[inside]]
    valid = observed > 0
    if int(valid.sum()) < 100:  # too little overlap to say
        return float("nan")
    return float(((observed[valid] - z[inside][valid]).abs() <= tolerance).double().mean())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data")
    parser.add_argument("--n", type=int, default=8, help="input views N (of the split for N = 2, 4, 8, 16)")
    parser.add_argument("--method", default="canonical")
    parser.add_argument("--scale", type=float, default=1.0)
    args = parser.parse_args()
    (method,) = check_methods([args.method])
    sequence = load_dataset(args.data)
    views = allowed_views(len(sequence), (2, 4, 8, 16))
    if args.n not in views:
        parser.error(f"--n: {args.n} is not among the input counts this capture allows, {list(views)}")
    split = interpolation_split(len(sequence), views)
    positions = split.inputs[args.n]
    frames = {p: resize_frame(sequence[p], args.scale) for p in sorted(set(split.heldout).union(*split.inputs.values()))}
    targets = [frames[p] for p in split.heldout]
    voxel = default_voxel_size([frames[p] for p in split.inputs[max(views)]])
    print(machine_summary())
    print(f"{sequence.name}: {method}, N = {args.n}, voxel {voxel:g}; inputs {list(positions)}, held out {list(split.heldout)}\n")

    def row(name: str, scores: list[float]) -> dict:
        return {"inputs": name, **{f"held-out {p}": f"{s:.2f}" for p, s in zip(split.heldout, scores)},
                "mean": f"{np.nanmean(scores):.2f}"}

    rows = [row("all", held_out_psnr(method, [frames[p] for p in positions], targets, voxel))]
    for left in positions:
        rows.append(row(f"without {left}", held_out_psnr(method, [frames[p] for p in positions if p != left], targets, voxel)))
        print(f"without {left} done", file=sys.stderr, flush=True)
    print_table(f"Held-out covered PSNR (dB), {sequence.name}", rows)

    tolerance = DEPTH_TOLERANCE_VOXELS * voxel
    matrix = [{"from \\ into": str(i), **{str(j): "" if i == j else f"{depth_agreement(frames[i], frames[j], tolerance):.2f}"
                                          for j in positions}} for i in positions]
    print_table(f"Inputs' depth lifted into each other: share within {tolerance * 100:.1f} cm", matrix)
    return 0


if __name__ == "__main__":
    sys.exit(main())
