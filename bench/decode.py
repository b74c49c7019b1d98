"""Decode benchmark: ms to turn a fused scene into Gaussians, as a render after a fold pays it.

    python bench/decode.py [--data ../shared/data/realsense_shelf] [--voxel 0.004] [--frames 10,25,50]

For the first F frames of the capture folded at the voxel size, medians of --repeats runs of:
`Scene.decode_inputs` (a copy of every sum), `Scene.decode_from`
from scratch (fields of the decoded voxels, the per-voxel SH solve, the decoder), and
`decode_from` right after each of the last --repeats folds (only the voxels the fold touched are
decoded again; `scene.decoded`); `Scene.gaussians` after each of those folds, as a viewer rendering
while a stream folds pays it (without F_scene for a colour render, with it for a feature map), and
the part of it that holds the scene's lock (which folds wait for: the rows that decode, and a copy
of what the decode reads of them); and, on the decoded
covariances, the decoder's eigen-decomposition on both paths: the numba Jacobi kernel
(`decode.symmetric_eigh3`) against its reference, LAPACK's batched `torch.linalg.eigh`, with their
ratio, and the decode's own kernel over every decoded voxel (`scene.shapes.voxel_shapes`: the
moments to stds and rotations, the Jacobi rotations inside); and the same for the per-voxel SH
colour fit (`scene.fields.solve_sh`, a numba Cholesky kernel, against `solve_sh_reference`,
assembled [V, K, K] systems and `torch.linalg.solve`).
Prints tables and the machine; asserts nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table, time_each  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.decode import symmetric_eigh3, symmetric_eigh3_reference  # noqa: E402
from canonical_core.scene import Scene, SceneConfig  # noqa: E402
from canonical_core.scene.fields import fields_from_sums, solve_sh, solve_sh_reference, sums_from_stored  # noqa: E402
from canonical_core.scene.selection import decoded_rows  # noqa: E402
from canonical_core.scene.shapes import voxel_shapes  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up: numba cache, allocator
    return statistics.median(time_each(lambda _: fn(), range(repeats)))


def timed(fn, ms: list[float]):
    """``fn``, appending the milliseconds of each call to ``ms``."""
    def clocked(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            ms.append((time.perf_counter() - t0) * 1000)
    return clocked


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="dataset folder (default: the shelf capture)")
    p.add_argument("--voxel", type=float, default=0.004)
    p.add_argument("--frames", default="10,25,50", help="comma-separated frame counts to fold (from the start)")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    try:
        counts = sorted({int(x) for x in args.frames.split(",") if x.strip()})
    except ValueError:
        p.error(f"--frames: expected comma-separated integers, got {args.frames!r}")
    if not counts or counts[0] < 1:
        p.error(f"--frames: expected positive counts, got {args.frames!r}")
    sequence = load_dataset(args.data)
    counts = [n for n in counts if n <= len(sequence)] or [len(sequence)]
    print(machine_summary())
    print(f"data: {args.data.name}, {len(sequence)} frames; voxel {args.voxel * 1000:g} mm; medians of {args.repeats}\n")

    decode_rows, eigen_rows, sh_rows = [], [], []
    # the viewed scenes fold the same frames and are decoded the way a service does it
    # (`Scene.gaussians`): for a colour render (no F_scene) and for a feature map (with it); the part
    # of each decode that holds the scene's lock is timed on its own
    # the decode alone: the colour solve off (a service's render shows the last solution and never
    # solves; what applying one adds is `python bench/colour_solve.py --costs`)
    config = SceneConfig(voxel_size=args.voxel, colour_solve={"views": 0})
    scene, folded = Scene(config), 0
    viewed = {features: Scene(config) for features in (False, True)}
    held: dict[bool, list[float]] = {features: [] for features in viewed}
    for features, v in viewed.items():
        v._decoding.take = timed(v._decoding.take, held[features])
    for n in counts:
        # the last `repeats` frames before n are folded one at a time, each followed by a decode as a
        # viewer's render would ask for it (reusing the voxels the fold left alone)
        last = max(folded, n - args.repeats)
        for position in range(folded, last):
            for s in (scene, *viewed.values()):
                s.fold(sequence[position])
        scene.decode()
        for features, v in viewed.items():
            v.gaussians(features=features)
            held[features].clear()
        after_fold, touched = [], []
        rendered: dict[bool, list[float]] = {features: [] for features in viewed}
        for position in range(last, n):
            report = scene.fold(sequence[position])
            touched.append(report.new_voxels + report.updated_voxels)
            inputs = scene.decode_inputs()
            after_fold += time_each(scene.decode_from, [inputs])
            for features, v in viewed.items():
                v.fold(sequence[position])
                rendered[features] += time_each(lambda _: v.gaussians(features=features), [0])
        folded = n
        inputs = scene.decode_inputs()
        gaussians = scene.decode_from(inputs)
        from_scratch = median_ms(lambda: scene.decode_from(inputs._replace(changed_at=None)), args.repeats)
        after = statistics.median(after_fold) if after_fold else float("nan")
        decode_rows.append({
            "frames": n, "voxels": len(scene), "Gaussians": len(gaussians),
            "voxels a fold touches": f"{statistics.median(touched):.0f}" if touched else "-",
            "decode_inputs ms": f"{median_ms(scene.decode_inputs, args.repeats):.1f}",
            "decode_from, from scratch ms": f"{from_scratch:.1f}",
            "decode_from after a fold ms": f"{after:.1f}",
            "ratio": f"{from_scratch / after:.1f}x",
            **{f"gaussians({'' if features else 'features=False'}) after a fold ms, under the lock":
               f"{statistics.median(rendered[features]):.1f}, {statistics.median(held[features]):.1f}"
               if rendered[features] else "-" for features in (False, True)},
        })
        cov = fields_from_sums(inputs.sums, scene.config, sort=False)["position_cov"] / args.voxel**2
        fast = median_ms(lambda: symmetric_eigh3(cov), args.repeats)
        lapack = median_ms(lambda: symmetric_eigh3_reference(cov), args.repeats)
        rows = decoded_rows(inputs.sums, 0.0, scene.config).rows
        shapes = median_ms(lambda: voxel_shapes(inputs.sums, rows, args.voxel, scene.config.research.eps,
                                                scene.decoder), args.repeats)
        eigen_rows.append({"frames": n, "matrices": len(cov), "numba Jacobi ms": f"{fast:.1f}",
                           "torch.linalg.eigh ms": f"{lapack:.1f}", "ratio": f"{lapack / fast:.1f}x",
                           "the decode's shapes kernel, decoded voxels ms": f"{len(rows)}: {shapes:.1f}"})
        sums = sums_from_stored({k: torch.as_tensor(np.ascontiguousarray(v)) for k, v in inputs.sums.items()})
        system = (sums["r_sum"] + scene.config.research.eps, sums["rgb_sum"], sums["sh_a"], sums["sh_b"],
                  scene.config.decoder.sh_regularization)
        fast = median_ms(lambda: solve_sh(*system), args.repeats)
        batched = median_ms(lambda: solve_sh_reference(*system), args.repeats)
        sh_rows.append({"frames": n, "systems": len(sums["r_sum"]), "K": sums["sh_b"].shape[1] // 3 + 1,
                        "numba Cholesky ms": f"{fast:.1f}", "torch.linalg.solve ms": f"{batched:.1f}",
                        "ratio": f"{batched / fast:.1f}x"})
    print_table("Decode of the fused scene (decode_inputs + decode_from: the library's copy, then its decode; "
                "gaussians(features=False): what a service's colour render pays, gaussians(): a feature map's; "
                "each with the part under the scene's lock)", decode_rows)
    print_table("Eigen-decomposition of the voxels' covariances, both paths (every voxel)", eigen_rows)
    print_table("SH colour fit, both paths (every voxel's K x K normal equations)", sh_rows)


if __name__ == "__main__":
    main()
