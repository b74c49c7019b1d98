"""Gaussian exports: time and peak memory of writing a scene's PLY and .splat, a block of rows at a
time (what `save_ply` / `save_splat` and the service's export routes do) against the whole file
encoded at once (``ply_bytes`` / ``splat_bytes`` written in one piece: what exports did before).

    python bench/export.py [--gaussians 250000 1000000] [--repeats 3]

The Gaussians are random, with the decoder's layout (SH degree 1, 16 feature channels): the cost of
an export depends on their count and channels, not their values. Each run is a process of its own
(the allocator keeps what an earlier run freed, which would hide a later run's rise): it makes the
Gaussians, then writes the file to a temporary folder; its peak memory is the resident set's rise
above where it stood before the write (`common.peak_growth`). Prints the tables with medians and the
machine; never asserts timings.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, peak_growth, print_table  # noqa: E402

from canonical_core import Gaussians, SceneConfig  # noqa: E402
from canonical_core.gaussians import ply_bytes, save_ply, save_splat, splat_bytes  # noqa: E402
from canonical_core.gaussians.io import atomic_write  # noqa: E402


def random_gaussians(n: int) -> Gaussians:
    config = SceneConfig(voxel_size=0.01)
    g = torch.Generator().manual_seed(0)
    return Gaussians(means=torch.randn(n, 3, generator=g), scales=torch.rand(n, 3, generator=g) * 0.01 + 1e-3,
                     quats=torch.randn(n, 4, generator=g), opacities=torch.rand(n, generator=g),
                     sh=torch.randn(n, (config.sh_degree + 1) ** 2, 3, generator=g),
                     features=torch.randn(n, config.features.dim, generator=g))


WAYS = {"PLY, in blocks": lambda g, path: save_ply(g, path),
        "PLY, whole": lambda g, path: atomic_write(path, [ply_bytes(g)]),
        ".splat, in blocks": lambda g, path: save_splat(g, path),
        ".splat, whole": lambda g, path: atomic_write(path, [splat_bytes(g)])}


def one_run(way: str, n: int) -> None:
    """A run in this process: prints ``ms bytes_of_peak_rise file_bytes``."""
    gaussians = random_gaussians(n)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scene"
        ms, peak = peak_growth(WAYS[way], gaussians, path)
        print(ms, peak, path.stat().st_size)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gaussians", type=int, nargs="+", default=[250_000, 1_000_000])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--one", nargs=2, metavar=("WAY", "N"), help=argparse.SUPPRESS)  # a run's own process
    args = p.parse_args(argv)
    if args.one:
        return one_run(args.one[0], int(args.one[1]))
    print(machine_summary())
    rows = []
    for n in args.gaussians:
        for name in WAYS:
            runs = [[float(x) for x in subprocess.run([sys.executable, __file__, "--one", name, str(n)], check=True,
                                                       capture_output=True, text=True).stdout.split()]
                    for _ in range(args.repeats)]
            ms, peak, size = (np.median([r[k] for r in runs]) for k in range(3))
            rows.append({"Gaussians": n, "export": name, "file MB": f"{size / 1e6:.1f}", "ms (median)": f"{ms:.0f}",
                         "peak rise MiB (median)": f"{peak / 2**20:.0f}", "peak / file": f"{peak / size:.2f}"})
    print_table(f"Exports, {args.repeats} runs each, each in its own process", rows)


if __name__ == "__main__":
    main()
