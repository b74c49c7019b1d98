"""A trained decoder against the training-free one, with the evaluation protocol on a capture that
was never trained on.

    python bench/train_eval.py MODEL.safetensors [--dataset ../shared/data/realsense_shelf]
                               [--views 2,4,8,16] [--scale 1] [--out DIR]

Runs `eval.run.evaluate` with two scene methods that differ only in `SceneConfig.model`:
``canonical:model=none`` (training-free) and ``canonical:model=MODEL`` (trained), everything else the
``canonical`` method's settings; prints PSNR over all pixels and over covered pixels per N, and
the trained decoder's gain. The full report (results.json / results.md) goes to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from canonical_core.eval.run import evaluate


def compare(results: dict, free_label: str, trained_label: str) -> list[dict]:
    """Per N: both methods' PSNR (all pixels, covered) and the trained decoder's gain."""
    runs = {(r["method"], r["views"]): r for r in results["runs"] if r["noise"] == 0}
    rows = []
    for n in sorted({v for _, v in runs}):
        free, trained = runs[(free_label, n)], runs[(trained_label, n)]
        rows.append({"views": n, "psnr_free": free["psnr"], "psnr_trained": trained["psnr"],
                     "covered_free": free["psnr_covered"], "covered_trained": trained["psnr_covered"],
                     "coverage_free": free["coverage"], "coverage_trained": trained["coverage"],
                     "gain": trained["psnr"] - free["psnr"], "gain_covered": trained["psnr_covered"] - free["psnr_covered"]})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--dataset", type=Path, default=Path("../shared/data/realsense_shelf"))
    parser.add_argument("--views", default="2,4,8,16")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--out", type=Path, default=Path("out/train_eval"))
    args = parser.parse_args()
    free, trained = "canonical:model=none", f"canonical:model={args.model.resolve()}"
    results = evaluate(args.dataset, views=[int(v) for v in args.views.split(",")], methods=[free, trained],
                       out_dir=args.out, scale=args.scale, stability_views=[], extrapolation=False)
    rows = compare(results, free, trained)
    (args.out / "comparison.json").write_text(json.dumps(rows, indent=1))
    print("| N | PSNR free | PSNR trained | gain | covered free | covered trained | gain covered | coverage free / trained |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['views']} | {r['psnr_free']:.2f} | {r['psnr_trained']:.2f} | {r['gain']:+.2f} | {r['covered_free']:.2f} | "
              f"{r['covered_trained']:.2f} | {r['gain_covered']:+.2f} | {r['coverage_free']:.3f} / {r['coverage_trained']:.3f} |")


if __name__ == "__main__":
    main()
