"""A restart of the service on a long session: time until it serves, and its memory on the way.

    python bench/restart.py [--data ../shared/data/hololens_office] [--frames 1500] [--voxel 0.02]
                            [--rounds 2] [--base PATH]

Streams ``--frames`` frames into one session through the SDK (the capture played again and again,
each frame with its own ``frame_id``, as a long stream is), stops the service gracefully, then
starts it again on that data directory, ``--rounds`` times, alternating with ``--base`` (another
checkout of the project) where given. Each start is timed until ``/healthz`` answers (the sessions
are open then) while the service's memory is sampled every 20 ms: the peak of its resident memory,
of it the anonymous part (the heap: what the system cannot drop) and the file-backed part (mapped
files: page cache it can drop), and both once it serves. Prints the machine and a table; never
asserts.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, process_mib  # noqa: E402
from ingest import running_service  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.sdk import Client  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "hololens_office"


def fill(repo: Path, data_dir: Path, payloads: list[dict], frames: int, voxel: float) -> int:
    """One session of ``frames`` frames in ``data_dir``, streamed into ``repo``'s service (each tree
    writes the files it reads); its archive's bytes."""
    with running_service(repo, data_dir) as (url, _, _), Client(url) as client:
        session = client.create_session(voxel_size=voxel)
        sent = ({**p, "frame_id": f"{k}"} for k, p in zip(range(frames), itertools.cycle(payloads)))
        for k, _ in enumerate(session.add_frames(sent, in_flight=3), 1):
            if k % 250 == 0:
                print(f"  {k} frames", file=sys.stderr)
    return sum(p.stat().st_size for p in data_dir.rglob("archive.log"))


def one_start(repo: Path, data_dir: Path) -> dict:
    """A start of ``repo``'s service on ``data_dir``: seconds until it serves, memory peaks and after."""
    peaks: dict[str, float] = {}
    done = threading.Event()
    t0 = time.perf_counter()
    with running_service(repo, data_dir, sampled=lambda pid: _sample(pid, peaks, done)) as (url, service, _):
        ready = time.perf_counter() - t0
        done.set()
        time.sleep(1.0)
        after = process_mib(service.pid)
    return {"ready s": ready, **{f"peak {k}": v for k, v in peaks.items()}, **{f"serving {k}": v for k, v in after.items()}}


def _sample(pid: int, peaks: dict, done: threading.Event) -> None:
    def loop() -> None:
        while not done.is_set():
            for k, v in process_mib(pid).items():
                peaks[k] = max(peaks.get(k, 0.0), v)
            time.sleep(0.02)

    threading.Thread(target=loop, daemon=True).start()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--frames", type=int, default=1500)
    p.add_argument("--voxel", type=float, default=0.02)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--base", type=Path, default=None, help="also start this checkout, alternating with this tree")
    args = p.parse_args()
    print(machine_summary())
    trees = [("this tree", REPO)] + ([] if args.base is None else [(f"base tree {args.base}", args.base.resolve())])
    payloads = [frame_arrays(f, sensor_units=True) for f in load_dataset(args.data)]
    with tempfile.TemporaryDirectory() as tmp:
        dirs = {name: Path(tmp) / f"data{k}" for k, (name, _) in enumerate(trees)}
        for name, repo in trees:
            archive = fill(repo, dirs[name], payloads, args.frames, args.voxel)
            print(f"{name}: one session of {args.frames} frames of {args.data.name} at {args.voxel * 1000:g} mm; "
                  f"its archive {archive / 2**20:.0f} MiB")
        runs = {name: [] for name, _ in trees}
        for _ in range(args.rounds):
            for name, repo in trees:
                runs[name].append(one_start(repo, dirs[name]))
    rows = []
    for name, results in runs.items():
        row = {"tree": name}
        for key in results[0]:
            values = [r.get(key, float("nan")) for r in results]
            row[key] = f"{statistics.median(values):.1f} ({', '.join(f'{v:.1f}' for v in values)})"
        rows.append(row)
    print_table("Start on a long session: seconds until it serves; memory in MiB, median (each round)", rows)


if __name__ == "__main__":
    main()
