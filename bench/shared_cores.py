"""Shared-cores benchmark: fold time with a CPU hog on one core against the quiet fold, beside the
same ratio for Open3D's integrate, in the same run.

    python bench/shared_cores.py [--data ../shared/data/realsense_shelf] [--voxel 0.004] [--frames 20] [--rounds 3]

Each round times, on the same frames (a fresh scene or grid each pass): our fold on numba's threads
(one a core) and on one thread (what `CANONICAL_THREADS=1` gives the service's workers), and
Open3D's integrate, quiet; then the same with a CPU hog running (a child process
``python -c 'while 1: pass'``: one core's worth of another process's load, placed by the OS).
Prints the machine, the medians and the hog/quiet ratios (each round's, and of the medians over all
rounds). Other work on the machine moves the absolute figures: read the ratios, taken side by side.
Never asserts timings.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `canonical serve` sets it, before numba and torch load
import numba  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, stats_ms  # noqa: E402
from fold import DEFAULT_DATA, time_folds, time_open3d  # noqa: E402

from canonical_core import SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.open3d_tsdf import open3d_available  # noqa: E402

HOG = "while 1: pass"


def ours(threads: int):
    """A timer of our fold on ``threads`` of numba's threads."""
    def run(frames, config) -> list[float]:
        numba.set_num_threads(threads)
        try:
            return time_folds(frames, config)[0]
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return run


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--voxel", type=float, default=0.004)
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--rounds", type=int, default=3, help="quiet + hog measurements, alternated")
    args = p.parse_args(argv)
    if min(args.frames, args.rounds) < 1:
        p.error("--frames and --rounds: expected positive numbers")
    frames = list(load_dataset(args.data, max_frames=args.frames))
    config = SceneConfig(voxel_size=args.voxel)
    cores = numba.config.NUMBA_NUM_THREADS
    folds = {f"ours, {cores} threads": ours(cores), "ours, 1 thread": ours(1)}
    if open3d_available():
        folds["Open3D integrate"] = lambda fs, _config: time_open3d(fs, args.voxel)
    print(machine_summary())
    print(f"data: {args.data.name}, {len(frames)} frames at {frames[0].width}x{frames[0].height}, voxel "
          f"{args.voxel * 1000:g} mm; {args.rounds} rounds of quiet, then one CPU hog\n")
    for fold in folds.values():
        fold(frames[:2], config)  # compile / load the kernels outside the measurement

    ms = {(name, hog): [] for name in folds for hog in (False, True)}
    ratios: dict[str, list[float]] = {name: [] for name in folds}
    for _ in range(args.rounds):
        for hog in (False, True):
            hogger = subprocess.Popen([sys.executable, "-c", HOG]) if hog else None
            try:
                for name, fold in folds.items():
                    ms[name, hog].append(fold(frames, config))
            finally:
                if hogger is not None:
                    hogger.kill()
                    hogger.wait()
        for name in folds:
            ratios[name].append(np.median(ms[name, True][-1]) / np.median(ms[name, False][-1]))

    rows = []
    for name in folds:
        quiet, hogged = np.concatenate(ms[name, False]), np.concatenate(ms[name, True])
        rows.append({"fold": name, "quiet ms (med/min/max)": stats_ms(quiet), "with a hog ms (med/min/max)": stats_ms(hogged),
                     "hog / quiet (medians)": f"{np.median(hogged) / np.median(quiet):.2f}",
                     "per round": ", ".join(f"{r:.2f}" for r in ratios[name])})
    print_table("Fold per frame, quiet vs one CPU hog (same run, same frames)", rows)


if __name__ == "__main__":
    main()
