"""The service's resident memory while many sessions live at once, round after round.

    python bench/sessions_memory.py [--data ../shared/data/realsense_shelf] [--sessions 30] [--rounds 3]
                                    [--frames 3] [--scale 0.5] [--voxel 0.01] [--also NAME=VALUE[,NAME=VALUE]]

Starts the real service (`canonical serve`, its defaults, a temporary data directory) once per
configuration: as shipped, and with each ``--also``'s environment (``NAME=`` unsets NAME; default:
``MALLOC_MMAP_THRESHOLD_=1048576``, glibc's mmap threshold fixed at 1 MiB, so that no large block
comes from its heap). Each round makes ``--sessions`` sessions at
once (eight client threads), streams ``--frames`` frames of the capture into each and renders one
view of each, reads the service's resident memory (VmRSS) and the sessions' own count of their
memory (``memory_bytes``, what the memory budget adds up), then deletes them all and reads VmRSS
again. Rounds repeat the same work: memory that grows from round to round is memory the process
keeps and does not reuse. Prints the machine and a table per configuration; never asserts.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, process_mib  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service  # noqa: E402
from client.sdk import Client  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def resident_mb(pid: int) -> float:
    return process_mib(pid)["VmRSS"]


def one_round(client: Client, pid: int, payloads: list[dict], sessions: int, voxel: float) -> dict:
    def life(_) -> object:
        session = client.create_session(voxel_size=voxel)
        for p in payloads:
            session.add_frame(**p)
        h, w = payloads[0]["rgb"].shape[:2]
        session.render(payloads[0]["K"], payloads[0]["c2w"], w, h)
        return session

    with ThreadPoolExecutor(8) as pool:
        alive = list(pool.map(life, range(sessions)))
        counted = sum(s.stats()["memory_bytes"] for s in alive) / 2**20
        rss = resident_mb(pid)
        list(pool.map(lambda s: s.delete(), alive))
    return {"alive": rss, "counted": counted, "deleted": resident_mb(pid)}


def run(config: str, env: dict, payloads: list[dict], args) -> list[dict]:
    saved = {k: os.environ.get(k) for k in env}
    for k, v in env.items():
        if v:
            os.environ[k] = v
        else:
            os.environ.pop(k, None)
    try:
        with tempfile.TemporaryDirectory() as data_dir:
            port = free_port()
            service = start_service(port, Path(data_dir))
            try:
                with Client(f"http://127.0.0.1:{port}", timeout=600) as client:
                    start = resident_mb(service.pid)
                    rows = []
                    for k in range(args.rounds):
                        r = one_round(client, service.pid, payloads, args.sessions, args.voxel)
                        rows.append({"configuration": config, "round": k + 1, "RSS at start MB": f"{start:.0f}",
                                     "RSS with the sessions MB": f"{r['alive']:.0f}",
                                     "RSS a session MB": f"{(r['alive'] - start) / args.sessions:.1f}",
                                     "memory_bytes a session MB": f"{r['counted'] / args.sessions:.1f}",
                                     "RSS after the deletes MB": f"{r['deleted']:.0f}"})
                        print(rows[-1], file=sys.stderr, flush=True)
                    return rows
            finally:
                service.terminate()
                service.wait(60)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)  # unset before, or unset by the configuration
            else:
                os.environ[k] = v


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--sessions", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--voxel", type=float, default=0.01)
    parser.add_argument("--also", action="append", default=[], metavar="NAME=VALUE[,NAME=VALUE]",
                        help="another configuration: the service's environment with these variables")
    args = parser.parse_args()
    frames = load_dataset(args.data, stride=10, max_frames=args.frames)
    payloads = [frame_arrays(f, args.scale) for f in frames]
    configs = {"as shipped": {}}
    for also in args.also or ["MALLOC_MMAP_THRESHOLD_=1048576"]:
        configs[also] = dict(item.split("=", 1) for item in also.split(","))
    print(machine_summary())
    rows = [row for name, env in configs.items() for row in run(name, env, payloads, args)]
    print_table(f"{args.sessions} sessions at once, {args.frames} frames of {args.data.name} each at scale {args.scale}, "
                f"voxel {args.voxel} m, one render each; {args.rounds} rounds", rows)
    for name in configs:
        last = [float(r["RSS a session MB"]) for r in rows if r["configuration"] == name]
        print(f"{name}: median RSS a session {statistics.median(last):.1f} MB, last round {last[-1]:.1f} MB")


if __name__ == "__main__":
    main()
