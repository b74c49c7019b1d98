"""Depth-stage benchmark: ms per frame of the plane sweep, and (optionally) its accuracy.

    python bench/depth.py [--data ../shared/data/realsense_shelf] [--repeats 7] [--accuracy]

Timing: one reference frame swept against 2 source views at 320x240 and 640x480 (sweep at half
resolution, the default), 32 and 64 hypotheses, on 2 threads. "total" is the whole depth stage
for an arriving frame: its matching features (the sources' come from the window), the sweep,
softmax / moments and upsampling. Medians / min / max over the repeats; never asserts timings.

--accuracy (a few minutes): median AbsRel against the sensor depth (withheld from the estimator)
for 1, 2 and 4 sources, best sources among all frames ("offline") and a session's window of past
frames ("stream"); sparsification (AUSE, the certain-half ratio) and a sharpness sweep.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table, stats_ms  # noqa: E402

from canonical_core.datasets import load_dataset, synthetic_rgbd  # noqa: E402
from canonical_core.evidence.matching import MATCH_SHARPNESS, MATCHING_FEATURE_DIM  # noqa: E402
from canonical_core.eval.mvs_eval import (  # noqa: E402
    LogitScale,
    offline_depth,
    stream_depth,
    summarize,
    without_depth,
)
from canonical_core.evidence.mvs import depth_hypotheses, upsample_depth  # noqa: E402
from canonical_core.evidence.source_views import SourceView  # noqa: E402
from canonical_core.evidence.sweep import depth_distribution, plane_sweep  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"
NEAR, FAR = 0.2, 2.0


def time_stage(ref_frame, sources: list[SourceView], K: int, repeats: int) -> dict[str, list[float]]:
    out = {k: [] for k in ("features", "sweep", "softmax+moments", "upsample", "total")}
    hyps = depth_hypotheses(NEAR, FAR, K)
    for _ in range(repeats):
        t0 = time.perf_counter()
        ref = SourceView.from_frame(ref_frame)
        t1 = time.perf_counter()
        logits, count = plane_sweep(ref, sources, hyps)
        t2 = time.perf_counter()
        D, U, _, valid = depth_distribution(logits, count, hyps)
        t3 = time.perf_counter()
        upsample_depth(np.where(valid, D, 0).astype(np.float32), np.where(valid, U, 0).astype(np.float32),
                       (ref_frame.height, ref_frame.width))
        t4 = time.perf_counter()
        for key, a, b in (("features", t0, t1), ("sweep", t1, t2), ("softmax+moments", t2, t3),
                          ("upsample", t3, t4), ("total", t0, t4)):
            out[key].append((b - a) * 1000)
    return out


def accuracy(frames, quick: bool) -> None:
    refs = list(range(0, len(frames), 2 if quick else 1))
    rows, curves = [], {}
    for k in (1, 2, 4):
        t0 = time.perf_counter()
        s = summarize(offline_depth(frames, refs, num_sources=k, near=NEAR, far=FAR, typical_depth=0.45))
        rows.append(_acc_row(f"offline, {k} source{'s' * (k > 1)}", s, time.perf_counter() - t0))
        curves[f"offline k={k}"] = s
    for k in (1, 2, 4):
        t0 = time.perf_counter()
        s = summarize(stream_depth(frames, num_sources=k, near=NEAR, far=FAR))
        rows.append(_acc_row(f"stream, {k} source{'s' * (k > 1)}", s, time.perf_counter() - t0))
        curves[f"stream k={k}"] = s
    print_table(f"Depth accuracy vs sensor depth ({len(refs)} offline reference frames, {len(frames)} streamed; "
                f"near/far {NEAR}/{FAR} m, 64 hypotheses, sweep at 1/2 resolution)", rows)
    sp_rows = []
    for name, s in curves.items():
        sp = s["sparsification"]
        row = {"protocol": name}
        for f in (0.0, 0.2, 0.4, 0.5, 0.6, 0.8, 0.95):
            i = int(np.argmin(np.abs(sp["fractions"] - f)))
            row[f"drop {int(f * 100)}%"] = f"{sp['curve'][i]:.4f}"
        row["oracle @50%"] = f"{sp['oracle'][int(np.argmin(np.abs(sp['fractions'] - 0.5)))]:.4f}"
        row["AUSE"] = f"{sp['ause']:.4f}"
        row["monotone"] = str(sp["monotone"])
        sp_rows.append(row)
    print_table("Sparsification: mean AbsRel of the pixels kept after dropping the most uncertain share", sp_rows)

    sharp_rows = []
    for s_factor in (1 / 1000, 8 / 28, 16 / 28, 1.0, 40 / 28, 56 / 28):
        s = summarize(offline_depth(frames, refs[::2], num_sources=2, near=NEAR, far=FAR, typical_depth=0.45,
                                    refine=LogitScale(s_factor)))
        label = "~unit-norm features" if s_factor < 0.01 else f"{MATCH_SHARPNESS * s_factor:.0f}"
        sharp_rows.append({"sharpness (logits / NCC / level)": label, "median AbsRel": f"{s['median_abs_rel']:.4f}",
                           "within 5 %": f"{s['within_5pct']:.3f}", "AUSE": f"{s['ause']:.4f}",
                           "certain-half ratio": f"{s['certain_half_ratio']:.3f}",
                           "median U_pos mm": f"{s['median_uncertainty'] * 1000:.1f}"})
    print_table(f"Sharpness of the sweep's softmax (offline, 2 sources, {len(refs[::2])} frames); the default is "
                f"{MATCH_SHARPNESS:g}. 'unit-norm': scores within +-1/sqrt(L) as with unit-norm features", sharp_rows)


def _acc_row(name, s, seconds) -> dict:
    return {"protocol": name, "frames": s["frames"], "median AbsRel": f"{s['median_abs_rel']:.4f}",
            "mean AbsRel": f"{s['mean_abs_rel']:.3f}", "within 5 %": f"{s['within_5pct']:.3f}",
            "coverage": f"{s['coverage']:.3f}", "AUSE": f"{s['ause']:.4f}",
            "certain-half / all (median)": f"{s['certain_half_ratio']:.3f}", "s": f"{seconds:.0f}"}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="dataset folder (default: the shelf capture)")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--accuracy", action="store_true", help="also measure accuracy against the sensor depth")
    p.add_argument("--quick", action="store_true", help="accuracy on every other frame only")
    args = p.parse_args(argv)
    torch.set_num_threads(2)
    numba.set_num_threads(2)

    if args.data.is_dir():
        seq = load_dataset(args.data)
        name = args.data.name
    else:
        seq = synthetic_rgbd(num_frames=50, width=640, height=480)
        name = "synthetic (../shared/data not found)"
    print(machine_summary())
    idx = (min(12, len(seq) - 3), min(20, len(seq) - 2), min(28, len(seq) - 1))
    full = [without_depth(seq[i]) for i in idx]
    print(f"data: {name}; reference frame {full[1].frame_id}, sources {full[0].frame_id} and {full[2].frame_id}; "
          f"matching features L = {MATCHING_FEATURE_DIM} (int8); near/far {NEAR}/{FAR} m; {args.repeats} repeats\n")
    rows = []
    for label, factor in (("320x240", 2), ("640x480", 1)):
        frames = [resize_frame(f, 1.0 / factor) for f in full]
        sources = [SourceView.from_frame(frames[0]), SourceView.from_frame(frames[2])]
        time_stage(frames[1], sources, 8, 1)  # compile / load the numba cache outside the measurement
        for K in (32, 64):
            t = time_stage(frames[1], sources, K, args.repeats)
            h, w = sources[0].features.shape[:2]
            rows.append({"image": label, "sweep": f"{w}x{h}", "sources": 2, "hypotheses": K,
                         "total ms (med/min/max)": stats_ms(t["total"]),
                         "features ms": f"{np.median(t['features']):.1f}",
                         "sweep ms": f"{np.median(t['sweep']):.1f}",
                         "softmax+moments ms": f"{np.median(t['softmax+moments']):.1f}",
                         "upsample ms": f"{np.median(t['upsample']):.1f}",
                         "window bytes/view": f"{sources[0].nbytes:,}"})
    print_table("Depth stage per frame (2 threads; source views precomputed, as in a session's window)", rows)

    if args.accuracy:
        frames = list(seq)
        if frames[0].depth is None:
            print("accuracy: the dataset has no sensor depth to compare with\n")
            return
        accuracy(frames, args.quick)


if __name__ == "__main__":
    main()
