"""Fold benchmark: ms per frame, growth behaviour on a long stream, bytes per voxel, Open3D peer.

    python bench/fold.py [--data ../shared/data/realsense_shelf] [--voxel 0.004]
                         [--long-data ../shared/data/hololens_office] [--long-voxel 0.01] [--long-passes 2] [--long-repeats 3]

Prints tables (medians, min, max) and the machine they ran on. Never asserts timings. Open3D's
VoxelBlockGrid TSDF integration runs on the same frames and voxel size in the same run when the
`bench` extra is installed (``pip install -e '.[bench]'``; Debian needs ``libusb-1.0-0``). Open3D's
grid commits its blocks' memory when it is made, outside its timed integrate; the column "fold,
memory preallocated" does the same for the scene (`Scene.preallocate` of the voxels the run ends
with), so that both folds run on memory already faulted in.
"""

from __future__ import annotations

import argparse
import gc
import resource
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table, stats_ms, time_each  # noqa: E402

from canonical_core import Frame, SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset, synthetic_rgbd  # noqa: E402
from canonical_core.evidence import denoise_rough_depth, extract_evidence  # noqa: E402
from canonical_core.eval.open3d_tsdf import Open3DTSDF, open3d_available  # noqa: E402
from canonical_core.eval.run import add_depth_noise  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402
from canonical_core.scene import Scene  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DEFAULT_DATA = DATA / "realsense_shelf"
LONG_DATA = DATA / "hololens_office"
WINDOW = 20  # folds in the early and the late window of the long stream


def time_folds(frames, config: SceneConfig, preallocate: int = 0) -> tuple[list[float], Scene, float]:
    """ms of each fold, the scene, and the mean ms of CPU time a fold spent in the OS kernel (all
    threads: mostly page faults of memory the map grows into, which a VM can make several times dearer).
    With ``preallocate``, the scene commits that many voxels' memory before the first fold
    (`Scene.preallocate`, outside the timing), as Open3D's grid does for its blocks when it is made."""
    scene = Scene(config)
    scene.preallocate(preallocate)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_stime
    ms = time_each(scene.fold, frames)
    return ms, scene, (resource.getrusage(resource.RUSAGE_SELF).ru_stime - before) * 1000.0 / max(len(frames), 1)


def time_open3d(frames, voxel: float) -> list[float]:
    return time_each(Open3DTSDF(voxel).integrate, frames)


def time_denoise(frames, config: SceneConfig, repeats: int) -> list[dict]:
    """ms per frame of the rough-depth check (every frame with depth pays it) and of the whole
    denoising step on the evaluation's depth noise 0.25 (where the check fires and the median runs)."""
    sensor = config.sensor.in_effect(frames[0].depth)  # the family a scene of these frames chooses

    def step(f):
        denoise_rough_depth(f.depth.numpy(), None, config.depth.denoise_radius, sensor.sigma0, sensor.sigma2,
                            sensor.sigma_ref)

    noisy = [add_depth_noise(f, 0.25, k) for k, f in enumerate(frames)]
    step(noisy[0])  # compile / load the numba cache outside the measurement
    rows = []
    for label, fs in (("clean (check only)", frames), ("depth noise 0.25 (check + median)", noisy)):
        ms = [t for _ in range(repeats) for t in time_each(step, fs)]
        rows.append({"depth": label, "ms per frame (med/min/max)": stats_ms(ms)})
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="dataset folder (default: the shelf capture)")
    p.add_argument("--voxel", type=float, default=0.004)
    p.add_argument("--repeats", type=int, default=3, help="passes over the frames per measurement")
    p.add_argument("--long-data", type=Path, default=LONG_DATA, help="capture of the long-stream test (default: the office walk)")
    p.add_argument("--long-voxel", type=float, default=0.01)
    p.add_argument("--long-passes", type=int, default=2, help="times the long stream plays the capture (0: skip the test)")
    p.add_argument("--long-repeats", type=int, default=3, help="runs of the long stream")
    args = p.parse_args(argv)

    frames = list(load_dataset(args.data)) if args.data.is_dir() else list(synthetic_rgbd(num_frames=50, width=640, height=480))
    name = args.data.name if args.data.is_dir() else "synthetic (../shared/data not found)"
    print(machine_summary())
    print(f"data: {name}, {len(frames)} frames, {frames[0].width}x{frames[0].height}; voxel {args.voxel * 1000:g} mm; "
          f"feature dim 16; each row: {args.repeats} passes over all frames, fresh scene per pass\n")
    config = SceneConfig(voxel_size=args.voxel)
    # Open3D's integrate has no counterpart of our free-space (see-through) evidence: the column
    # without it compares evidence + aggregation alone, the work both do
    no_free_space = config.replace(free_space={"enabled": False})
    # opt-in: frames with depth are also swept against earlier views to fill their depth's large holes
    completion = config.replace(depth={"completion": True})
    time_folds(frames[:2], completion)  # compile / load the numba cache outside the measurement

    rows = []
    have_o3d = open3d_available()
    for factor in (1, 2):  # full size, then half
        fs = [resize_frame(f, 1.0 / factor) for f in frames]
        label = f"{fs[0].camera.width}x{fs[0].camera.height}"
        fold_ms, os_ms, ev_ms, o3d_ms, agg_ms, completion_ms, reserved_ms, scene = [], [], [], [], [], [], [], None
        for _ in range(args.repeats):
            ms, scene, in_os = time_folds(fs, config)
            fold_ms += ms
            os_ms.append(in_os)
            reserved_ms += time_folds(fs, config, preallocate=len(scene))[0]
            agg_ms += time_folds(fs, no_free_space)[0]
            completion_ms += time_folds(fs, completion)[0]
            ev_ms += time_each(lambda f: extract_evidence(f, config), fs)
            if have_o3d:
                o3d_ms += time_open3d(fs, args.voxel)
        row = {"size": label, "fold ms (med/min/max)": stats_ms(fold_ms),
               "CPU ms in the OS kernel a fold (mean per pass)": " / ".join(f"{v:.1f}" for v in os_ms),
               "of which evidence ms": stats_ms(ev_ms),
               "fold without free space ms": stats_ms(agg_ms), "fold with depth.completion ms": stats_ms(completion_ms),
               "fold, memory preallocated ms": stats_ms(reserved_ms)}
        if have_o3d:
            row["Open3D integrate ms"] = stats_ms(o3d_ms)
            row["ratio ours/Open3D (median)"] = f"{np.median(fold_ms) / np.median(o3d_ms):.2f}"
            row["ratio preallocated"] = f"{np.median(reserved_ms) / np.median(o3d_ms):.2f}"
            row["ratio without free space"] = f"{np.median(agg_ms) / np.median(o3d_ms):.2f}"
        row["voxels"] = f"{len(scene):,}"
        row["bytes/voxel"] = f"{scene.bytes_per_voxel():.0f}"
        row["allocated bytes/voxel"] = f"{scene.memory_bytes() / len(scene):.0f}"
        rows.append(row)
    print_table("Fold per frame (evidence + aggregation)", rows)
    if not have_o3d:
        print("Open3D not installed: install the `bench` extra for the peer column.\n")
    print_table(f"Depth denoising, {frames[0].camera.width}x{frames[0].camera.height}, radius {config.depth.denoise_radius} (part of the fold above)",
                time_denoise(frames, config, args.repeats))

    if args.long_passes == 0 or not args.long_data.is_dir():
        return
    long_stream(list(load_dataset(args.long_data)) * args.long_passes, args.long_data.name, args.long_voxel,
                args.long_passes, args.long_repeats)


def long_stream(stream: list[Frame], name: str, voxel: float, passes: int, repeats: int) -> None:
    """A growing map: fold time of the last `WINDOW` folds over the first, and the slowest fold over
    the median (a fold that pays for the map's growth stands out). The ratio compares different
    frames of one stream, so a burst of load on a shared machine moves it: each run is printed.
    Then, after one decode (whose decoded rows the scene keeps), the scene's `memory_bytes` per voxel
    against the growth of the process's resident memory over the run."""
    config = SceneConfig(voxel_size=voxel)
    time_folds(stream[:2], config)  # compile / load the numba cache outside the measurement

    def row(run, ms: list[float], scene: Scene) -> dict:
        median = np.median(ms)
        first, last = [t for m in ms for t in m[:WINDOW]], [t for m in ms for t in m[-WINDOW:]]
        return {"run": run, "median ms": f"{median:.1f}", f"first {WINDOW} ms": f"{np.median(first):.1f}",
                f"last {WINDOW} ms": f"{np.median(last):.1f}", "ratio last/first": f"{np.median(last) / np.median(first):.2f}",
                "slowest ms": f"{np.max(ms):.0f}", "slowest/median": f"{np.max(ms) / median:.1f}",
                "voxels at the end": f"{len(scene):,}", "state bytes/voxel": f"{scene.bytes_per_voxel():.0f}"}

    runs, rows = [], []
    for run in range(repeats):
        gc.collect()
        before = resident_bytes()
        ms, scene, in_os = time_folds(stream, config)
        runs.append(ms)
        rows.append(row(run + 1, [ms], scene) | {"CPU ms in the OS kernel a fold": f"{in_os:.1f}"})
        gaussians = len(scene.decode())
        gc.collect()
        rows[-1] |= {"Gaussians": f"{gaussians:,}", "memory_bytes/voxel": f"{scene.memory_bytes() / len(scene):.0f}",
                     "RSS growth/voxel": f"{(resident_bytes() - before) / len(scene):.0f}"}
        if run < repeats - 1:
            del scene
    rows.append(row("all (windows pooled)", runs, scene))
    print_table(f"Long stream: {name} played {passes} times ({len(stream)} folds) at {voxel * 1000:g} mm, "
                f"defaults; targets: ratio <= 1.2, slowest <= 3x the median; memory <= 250 bytes/voxel", rows)


def resident_bytes() -> int:
    """The process's resident memory (VmRSS)."""
    line = next(ln for ln in Path("/proc/self/status").read_text().splitlines() if ln.startswith("VmRSS:"))
    return int(line.split()[1]) * 1024


if __name__ == "__main__":
    torch.set_num_threads(2)
    main()
