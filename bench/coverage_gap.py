"""What the pixels that only `no_free_space` covers are: carved surface or painted floaters.

    python bench/coverage_gap.py [--data ../shared/data/realsense_shelf] [--views 4,8] [--out DIR]

With the evaluation's protocol and scoring (`canonical_core.eval`), per N: the held-out pixels that
`no_free_space` covers and `canonical` does not, split by what the held-out frame's own sensor says
there (no depth / depth within 2 voxels of no_free_space's rendered depth / depth elsewhere), and
the all-pixel squared error the two methods gain over each other on those pixels and on the
pixels both cover. The all-pixel PSNR difference (of the squared error pooled over the held-out
frames; the evaluation averages per-frame PSNR, so its figure differs a little) is the sum of the
two parts. ``--out`` writes
``coverage_gap_N{n}.png``: ground truth, both renders and the extra pixels coloured by class (red: no
sensor depth, green: agrees, yellow: disagrees) for three held-out frames.
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
from canonical_core.eval.metrics import covered  # noqa: E402
from canonical_core.eval.figures import image_grid  # noqa: E402
from canonical_core.eval.run import default_voxel_size  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"
CLASS_COLOURS = {"no sensor depth": (255, 0, 0), "agrees": (0, 200, 0), "disagrees": (255, 220, 0)}


def _uint8(rgb: torch.Tensor) -> np.ndarray:  # [H, W, 3] in [0, 1] -> uint8
    return (rgb.clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def _db(se_a: float, se_b: float) -> float:
    """PSNR of a minus PSNR of b (dB), from their total squared errors over the same pixels."""
    return 10.0 * math.log10(se_b / se_a)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", default="4,8", help="comma-separated input view counts N")
    p.add_argument("--out", type=Path, default=None, help="folder for the PNG grids (default: none)")
    args = p.parse_args(argv)
    views = [int(v) for v in args.views.split(",")]
    frames, split, targets = held_out_split(args.data, views)
    voxel = default_voxel_size(frames)
    print(machine_summary())
    rows = []
    for n in views:
        inputs = [frames[i] for i in split.inputs[n]]
        full, _ = build("canonical", inputs, voxel)
        carved, _ = build("no_free_space", inputs, voxel)
        counts = dict.fromkeys(CLASS_COLOURS, 0)
        se = {"canonical": 0.0, "no_free_space": 0.0, "canonical, both cover": 0.0, "no_free_space, both cover": 0.0}
        columns: dict[str, list[np.ndarray]] = {"ground truth": [], "canonical": [], "no_free_space": [], "extra pixels": []}
        for k, target in enumerate(targets):
            gt = target.rgb.float() / 255.0
            a, b = full.render(target.camera), carved.render(target.camera)
            ca, cb = covered(a.alpha), covered(b.alpha)
            extra = cb & ~ca
            sensor = target.depth
            classes = {"no sensor depth": extra & (sensor <= 0),
                       "agrees": extra & (sensor > 0) & ((b.depth - sensor).abs() <= 2 * voxel),
                       "disagrees": extra & (sensor > 0) & ((b.depth - sensor).abs() > 2 * voxel)}
            for name, mask in classes.items():
                counts[name] += int(mask.sum())
            err_a, err_b = ((a.rgb - gt) ** 2).sum(-1), ((b.rgb - gt) ** 2).sum(-1)
            se["canonical"] += float(err_a.sum())
            se["no_free_space"] += float(err_b.sum())
            se["canonical, both cover"] += float(err_a[ca & cb].sum())
            se["no_free_space, both cover"] += float(err_b[ca & cb].sum())
            if args.out is not None and k in (0, len(targets) // 2, len(targets) - 1):
                overlay = (0.35 * gt * 255).to(torch.uint8).numpy()
                for name, mask in classes.items():
                    overlay[mask.numpy()] = CLASS_COLOURS[name]
                for name, img in zip(columns, (_uint8(gt), _uint8(a.rgb), _uint8(b.rgb), overlay)):
                    columns[name].append(img)
        extra_total = sum(counts.values())
        # between the two: canonical with no_free_space's errors on the pixels both cover
        between = se["canonical"] - se["canonical, both cover"] + se["no_free_space, both cover"]
        rows.append({
            "N": n,
            "extra pixels (share of all)": f"{extra_total / (len(targets) * targets[0].height * targets[0].width):.4f}",
            **{f"of which {name}": f"{c / max(extra_total, 1):.3f}" for name, c in counts.items()},
            "all-pixel dB canonical - no_free_space": f"{_db(se['canonical'], se['no_free_space']):+.2f}",
            "of it, on pixels both cover": f"{_db(se['canonical'], between):+.2f}",
            "of it, elsewhere": f"{_db(between, se['no_free_space']):+.2f}",
        })
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            image_grid(columns).save(args.out / f"coverage_gap_N{n}.png")
        print(f"N = {n} done", file=sys.stderr, flush=True)
    print_table(f"pixels only no_free_space covers: {len(targets)} held-out frames {list(split.heldout)}, "
                f"{targets[0].width}x{targets[0].height}, voxel {voxel * 1000:.2f} mm", rows)


if __name__ == "__main__":
    main()
