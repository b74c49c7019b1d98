"""Pose-correction benchmark: ms per corrected frame against ms per fold, for corrections of 1, 10
and 100 frames and of the whole session, against re-streaming the session; the archive's bytes per frame.

    python bench/poses.py [--data ../shared/data/hololens_office] [--scale 0.5] [--voxel 0.03] [--checkpoint-every 25]

A correction re-folds the corrected stream from an exact state before the first frame it touches,
so its cost depends on where its frames are: the most recent k frames (among the last folds' undo
records) cost about k folds, rolled back in place; k frames spread over the session (a loop
closure) cost a re-fold of nearly all of it from a saved state (a library checkpoint, or the
service's snapshot), which the service runs in the background past its threshold (the SDK polls
its status every half second until it is done). Both are measured, in-process
(`Scene.update_poses`) and over HTTP (`POST /v1/sessions/{id}/poses`, a real service started here),
next to re-streaming every frame. Prints tables and the machine they ran on; never asserts timings.

``--last K --of N`` also prints what correcting the last K of N frames costs against correcting all
N, in-process, each in its own scene as a service session keeps it (frames kept, the default undo
records): ms, the resident memory the correction adds at its peak, and the undo records' bytes.
For the office walk as the memory target reads it:

    python bench/poses.py --scale 1 --voxel 0.01 --last 5 --of 25 --tables last
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, peak_growth, print_table, time_each  # noqa: E402

from canonical_core import SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import SplatModel  # noqa: E402
from canonical_core.eval.run import score  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402
from canonical_core.scene import Scene  # noqa: E402
from canonical_core.scene.corrections import drift_walk, drifted  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service  # noqa: E402
from client.sdk import Client  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hololens_office"


def corrections(n: int) -> list[tuple[str, list[int]]]:
    """(label, positions) of the corrections measured: the most recent k frames and k spread evenly."""
    out = []
    for k in (1, 10, 100):
        if k <= n:
            out.append((f"{k} most recent", list(range(n - k, n))))
            if k > 1:
                out.append((f"{k} spread (loop closure)", np.linspace(0, n - 1, k).round().astype(int).tolist()))
    out.append((f"all {n}", list(range(n))))
    return out


def new_poses(frames, positions: list[int], seed: int) -> dict[int, np.ndarray]:
    """A small revision of the poses at ``positions`` (1 cm and 0.5 degrees of drift per 10 frames)."""
    walk = drift_walk(len(frames), 0.01, 0.5, every=10, seed=seed)
    return {k: walk[k] @ frames[k].camera.c2w64() for k in positions}


def row(label: str, k: int, ms: float, fold_ms: float) -> dict:
    return {"correction": label, "frames": k, "ms": f"{ms:.0f}", "ms per corrected frame": f"{ms / k:.1f}",
            "in folds": f"{ms / fold_ms:.1f}"}


def in_process(frames, voxel: float, checkpoint_every: int) -> tuple[list[dict], float]:
    Scene(SceneConfig(voxel_size=voxel)).fold(frames[0])  # load the kernels outside the measurement
    scene = Scene(SceneConfig(voxel_size=voxel), keep_frames=True, checkpoint_every=checkpoint_every)
    fold_ms = float(np.median(time_each(scene.fold, frames)))
    rows = [{"correction": "fold (per frame)", "frames": 1, "ms": f"{fold_ms:.1f}", "ms per corrected frame": "",
             "in folds": "1.0"}]
    for seed, (label, positions) in enumerate(corrections(len(frames))):
        t0 = time.perf_counter()
        scene.update_poses(new_poses(frames, positions, seed))
        rows.append(row(label, len(positions), (time.perf_counter() - t0) * 1000, fold_ms))
    return rows, fold_ms


def revision(frames, positions: list[int], seed: int) -> dict[int, np.ndarray]:
    """New poses for the contiguous ``positions``: the drift walk of `new_poses` started at the first
    of them, so a revision of the last frames moves them as little, against their neighbours, as a
    revision of all moves the first ones (the walk from frame 0 would move the last frames by the
    drift of all before them, and their re-fold would make new voxels that a revision of all does not)."""
    walk = drift_walk(len(positions), 0.01, 0.5, every=10, seed=seed)
    return {k: walk[i] @ frames[k].camera.c2w64() for i, k in enumerate(positions)}


def last_against_all(frames, voxel: float, last: int) -> list[dict]:
    """Correcting the last ``last`` of ``frames`` and correcting all of them (`revision`), each in a
    fresh scene that folded them all (frames kept, no checkpoints; the default undo records, and for
    the last ones also records of ``last`` folds, so that they roll back in place): ms, in folds, the
    peak resident growth, and the undo records' bytes before and after."""
    n, rows, fold_ms = len(frames), [], None
    # the kernels loaded, and a throwaway correction of them all made, outside the measurement: the
    # first large allocations of a process fault in fresh pages, which would fall on the first row
    warm = Scene(SceneConfig(voxel_size=voxel), keep_frames=True)
    for frame in frames:
        warm.fold(frame)
    warm.update_poses(revision(frames, list(range(n)), seed=n))
    del warm
    cases = ((f"the last {last}", None, list(range(n - last, n))),
             (f"the last {last}, records of {last} folds", last, list(range(n - last, n))),
             (f"all {n}", None, list(range(n))))
    for label, depth, positions in cases:
        scene = Scene(SceneConfig(voxel_size=voxel), keep_frames=True, undo_depth=depth)
        ms = time_each(scene.fold, frames)
        fold_ms = fold_ms or float(np.median(ms))
        undo_before = scene.undo_bytes()
        ms, peak = peak_growth(scene.update_poses, revision(frames, positions, seed=n))
        rows.append({"correction": label, "frames": len(positions), "ms": f"{ms:.0f}", "in folds": f"{ms / fold_ms:.1f}",
                     "peak resident growth MB": f"{peak / 1e6:.1f}", "undo MB before / after":
                     f"{undo_before / 1e6:.1f} / {scene.undo_bytes() / 1e6:.1f}",
                     "scene MB": f"{scene.memory_bytes() / 1e6:.1f}", "voxels": len(scene)})
    return rows


def drift_figures(frames, voxel: float, held_every: int) -> list[dict]:
    """Held-out figures of the clean fusion, of the drifted one (1 cm and 0.5 degrees per 10 frames),
    and of the drifted one after one correction with the true poses."""
    held = list(range(3, len(frames), held_every))
    inputs = [k for k in range(len(frames)) if k not in held]
    targets = [frames[k] for k in held]
    bad = drifted(frames, drift_walk(len(frames), 0.01, 0.5, every=10, seed=0))
    rows, digests = [], {}
    for label, stream in (("clean poses", frames), ("drifted poses", bad), ("drifted, then corrected", bad)):
        scene = Scene(SceneConfig(voxel_size=voxel), keep_frames=True)
        for k in inputs:
            scene.fold(stream[k])
        if label.endswith("corrected"):
            scene.update_poses({frames[k].frame_id: frames[k].camera.c2w64() for k in inputs})
        digests[label] = scene.digest()
        m = score(SplatModel(scene.gaussians()), targets, voxel).metrics
        rows.append({"fusion": label, "PSNR all (dB)": f"{m['psnr']:.2f}", "PSNR covered (dB)": f"{m['psnr_covered']:.2f}",
                     "depth agreement": f"{m['depth_agreement']:.3f}",
                     "digest = clean": str(digests[label] == digests["clean poses"]).lower()})
    return rows


def over_http(frames, voxel: float) -> tuple[list[dict], dict]:
    payloads = [frame_arrays(f) for f in frames]
    with tempfile.TemporaryDirectory() as data:
        port = free_port()
        proc = start_service(port, Path(data))
        try:
            with Client(f"http://127.0.0.1:{port}") as client:
                session = client.create_session(voxel_size=voxel)
                t0 = time.perf_counter()
                fold_ms = [session.add_frame(**p)["ms"] for p in payloads]
                stream_ms = (time.perf_counter() - t0) * 1000
                fold = float(np.median(fold_ms))
                rows = [{"correction": "re-stream the session", "frames": len(frames), "ms": f"{stream_ms:.0f}",
                         "ms per corrected frame": f"{stream_ms / len(frames):.1f}", "in folds": f"{stream_ms / fold:.1f}"}]
                for seed, (label, positions) in enumerate(corrections(len(frames))):
                    poses = {payloads[k]["frame_id"]: c2w for k, c2w in new_poses(frames, positions, seed).items()}
                    t0 = time.perf_counter()
                    session.update_poses(poses)
                    rows.append(row(label, len(positions), (time.perf_counter() - t0) * 1000, fold))
                stats = session.stats()
        finally:
            proc.terminate()
            proc.wait(60)
    return rows, stats


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--scale", type=float, default=0.5, help="resize frames by this factor")
    parser.add_argument("--stride", type=int, default=1)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--voxel", type=float, default=0.03)
    parser.add_argument("--checkpoint-every", type=int, default=25, help="library checkpoints (frames)")
    parser.add_argument("--snapshot-every", type=int, default=25, help="the service's snapshot_every_frames")
    parser.add_argument("--held-every", type=int, default=8, help="drift figures: every k-th frame held out")
    parser.add_argument("--last", type=int, default=5, help="the 'last K of N' table: K")
    parser.add_argument("--of", type=int, default=25, help="the 'last K of N' table: N (the first N frames)")
    parser.add_argument("--tables", default="drift,in-process,last,http", help="which tables, comma-separated")
    args = parser.parse_args(argv)
    tables = set(args.tables.split(","))
    frames = [resize_frame(f, args.scale) for f in load_dataset(args.data, stride=args.stride, max_frames=args.max_frames)]
    print(machine_summary())
    print(f"{args.data.name}: {len(frames)} frames at {frames[0].width}x{frames[0].height}, voxel {args.voxel} m\n")
    if "drift" in tables:
        print_table(f"drift and one correction: held-out views (every {args.held_every}th frame)",
                    drift_figures(frames, args.voxel, args.held_every))
    if "in-process" in tables:
        rows, _ = in_process(frames, args.voxel, args.checkpoint_every)
        print_table(f"in-process: Scene.update_poses (checkpoint every {args.checkpoint_every} frames)", rows)
    if "last" in tables:
        print_table(f"in-process: the last {args.last} of {args.of} frames corrected, against all {args.of}",
                    last_against_all(frames[: args.of], args.voxel, args.last))
    if "http" not in tables:
        return 0
    os.environ["CANONICAL_SNAPSHOT_EVERY_FRAMES"] = str(args.snapshot_every)
    os.environ.setdefault("CANONICAL_SNAPSHOT_EVERY_SECONDS", "3600")
    rows, stats = over_http(frames, args.voxel)
    print_table(f"over HTTP: POST /poses (snapshot every {args.snapshot_every} frames; 'in folds' = the server's "
                "median fold)", rows)
    print_table("frame archive", [{"frames": stats["archive_frames"], "bytes": stats["archive_bytes"],
                                   "bytes per frame": round(stats["archive_bytes"] / max(stats["archive_frames"], 1)),
                                   "raw rgb + float depth per frame": frames[0].width * frames[0].height * 7}])
    return 0


if __name__ == "__main__":
    sys.exit(main())
