"""Where canonical loses to a peer on the pixels both draw: depth edges or flat surfaces, and which.

    python bench/error_split.py [--data ../shared/data/sun3d_studyroom] [--views 16] [--peer open3d_tsdf] [--out DIR]

With the evaluation's protocol and scoring (`canonical_core.eval`, the defaults and its voxel
rule), per N: the held-out pixels that both `canonical` and the peer cover, split by the held-out
frame's own depth into the band near a depth edge (`eval.metrics.depth_edge_band`) and the rest
(flat), and in each part the PSNR of both (pooled squared error over the held-out frames: the
evaluation averages per-frame PSNR, so its figures differ a little) and the share of the pixels
where canonical's squared error is the larger. ``--out`` writes ``error_split_N{n}.png`` for three
held-out frames: ground truth, both renders, and where each is worse (red: canonical's error is the
larger by more than 0.01 of squared unit colour, blue: the peer's; grey: level; black: not drawn
by both), so that one sees what kind of surface the difference comes from.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import held_out_split, machine_summary, print_table  # noqa: E402

from canonical_core.eval.methods import build  # noqa: E402
from canonical_core.eval.metrics import covered, depth_edge_band  # noqa: E402
from canonical_core.eval.figures import image_grid  # noqa: E402
from canonical_core.eval.run import default_voxel_size  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "sun3d_studyroom"
LEVEL = 0.01  # squared-error difference (unit colour, summed over channels) below which a pixel is level


def _uint8(rgb: torch.Tensor) -> np.ndarray:  # [H, W, 3] in [0, 1] -> uint8
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def _psnr(se: float, count: int) -> float:  # pooled squared error over ``count`` pixels x 3 channels
    return 10.0 * math.log10(3 * count / se) if se > 0 else math.inf


def which_is_worse(err_a: torch.Tensor, err_b: torch.Tensor, both: torch.Tensor) -> np.ndarray:  # [H, W, 3] uint8
    """Red where a's squared error is the larger by more than `LEVEL`, blue where b's is, grey where
    they are level, black where not both draw."""
    out = np.zeros((*both.shape, 3), np.uint8)
    diff = (err_a - err_b).numpy()
    mask = both.numpy()
    out[mask] = (96, 96, 96)
    out[mask & (diff > LEVEL)] = (230, 40, 40)
    out[mask & (diff < -LEVEL)] = (40, 90, 230)
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", default="16", help="comma-separated input view counts N")
    p.add_argument("--peer", default="open3d_tsdf", help="the method to compare canonical with")
    p.add_argument("--out", type=Path, default=None, help="folder for the PNG grids (default: none)")
    args = p.parse_args(argv)
    views = [int(v) for v in args.views.split(",")]
    frames, split, targets = held_out_split(args.data, views)
    voxel = default_voxel_size([frames[i] for i in split.inputs[max(views)]])
    print(machine_summary())
    rows = []
    for n in views:
        inputs = [frames[i] for i in split.inputs[n]]
        ours, _ = build("canonical", inputs, voxel)
        peer, _ = build(args.peer, inputs, voxel)
        sums = {part: {"pixels": 0, "ours": 0.0, "peer": 0.0, "ours worse": 0} for part in ("edge", "flat")}
        columns: dict[str, list[np.ndarray]] = {"ground truth": [], "canonical": [], args.peer: [], "worse: red ours, blue peer": []}
        for k, target in enumerate(targets):
            gt = target.rgb.float() / 255.0
            a, b = ours.render(target.camera), peer.render(target.camera)
            both = covered(a.alpha) & covered(b.alpha)
            err_a, err_b = ((a.rgb - gt) ** 2).sum(-1), ((b.rgb - gt) ** 2).sum(-1)
            edge = depth_edge_band(target.depth)
            for part, mask in (("edge", both & edge), ("flat", both & ~edge)):
                sums[part]["pixels"] += int(mask.sum())
                sums[part]["ours"] += float(err_a[mask].sum())
                sums[part]["peer"] += float(err_b[mask].sum())
                sums[part]["ours worse"] += int((mask & (err_a - err_b > LEVEL)).sum())
            if args.out is not None and k in (0, len(targets) // 2, len(targets) - 1):
                for name, img in zip(columns, (_uint8(gt), _uint8(a.rgb), _uint8(b.rgb), which_is_worse(err_a, err_b, both))):
                    columns[name].append(img)
        total = sum(s["pixels"] for s in sums.values())
        for part, s in sums.items():
            rows.append({"N": n, "part": part, "share of common pixels": f"{s['pixels'] / max(total, 1):.2f}",
                         "canonical PSNR": f"{_psnr(s['ours'], s['pixels']):.2f}",
                         f"{args.peer} PSNR": f"{_psnr(s['peer'], s['pixels']):.2f}",
                         "lead dB": f"{_psnr(s['ours'], s['pixels']) - _psnr(s['peer'], s['pixels']):+.2f}",
                         "pixels where canonical is worse": f"{s['ours worse'] / max(s['pixels'], 1):.2f}"})
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            image_grid(columns).save(args.out / f"error_split_N{n}.png")
    print(f"data: {args.data.name}, {len(frames)} frames, voxel {voxel:g}, held out {list(split.heldout)}\n")
    print_table(f"canonical against {args.peer} on the pixels both cover: near a depth edge and flat", rows)


if __name__ == "__main__":
    main()
