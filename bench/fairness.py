"""Fairness benchmark: another session's frame latency, quiet vs during 10 looping large renders.

    python bench/fairness.py [--data ../shared/data/realsense_shelf] [--frames 20] [--voxel 0.004]
                             [--clients 10] [--render-size 1280x960] [--rounds 2]

Starts the real service (`canonical serve`, uvicorn, its default settings) on a free loopback port
with a temporary data directory and folds the first frames into session A. Then, ``--rounds`` times:
one client streams the frames into a fresh session, first alone (quiet), then while ``--clients``
clients loop large renders of session A (the SDK's msgpack view at ``--render-size``, asked again
at once, through the SDK's client, which waits out a 429's Retry-After and asks again), once they
have filled A's queue. The streaming client retries no 429 (`Client(max_retries=0)`), so every
refused frame counts. Prints the machine, the frame round trips quiet and loaded (medians over all
rounds, and each round's ratio), the frames taken, and the renders done and refused meanwhile. The
target: every frame taken, the loaded median within 2x of the quiet one. Never asserts timings.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, stats_ms  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service  # noqa: E402
from client.sdk import CanonicalError, Client, Session  # noqa: E402
from tests.server.harness import RenderLoop, wait_for  # noqa: E402  (the fairness test's load)

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def stream(url: str, payloads: list[dict], voxel: float) -> tuple[list[float], int]:
    """Fold ``payloads`` into a new session, one at a time: (round trips in ms of the frames taken,
    frames refused with 429). The session is made and deleted through a client that retries 429s."""
    times, refused = [], 0
    with Client(url) as patient, Client(url, max_retries=0) as strict:
        session = patient.create_session(voxel_size=voxel)
        frames = Session(strict, session.id, label_dim=0)
        for p in payloads:
            t0 = time.perf_counter()
            try:
                frames.add_frame(**p)
            except CanonicalError as exc:
                if exc.status != 429:
                    raise
                refused += 1
                continue
            times.append((time.perf_counter() - t0) * 1000)
        session.delete()
    return times, refused


def ratio(loaded: list[float], quiet: list[float]) -> str:
    """The median of ``loaded`` over the median of ``quiet``; "-" where no frame was taken under load."""
    return f"{statistics.median(loaded) / statistics.median(quiet):.2f}" if loaded else "-"


def refusals(url: str) -> int:
    """The 429s the service answered since it started (its /metrics)."""
    text = httpx.get(f"{url}/metrics").text
    return sum(int(line.split()[-1]) for line in text.splitlines() if line.startswith('canonical_http_responses_total{status="429"}'))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--voxel", type=float, default=0.004)
    p.add_argument("--frames", type=int, default=20, help="frames each stream sends")
    p.add_argument("--clients", type=int, default=10, help="clients looping renders of the other session")
    p.add_argument("--render-size", default="1280x960", help="WIDTHxHEIGHT of the looping renders")
    p.add_argument("--rounds", type=int, default=2, help="quiet + loaded streams, alternated")
    args = p.parse_args(argv)
    try:
        size = tuple(int(v) for v in args.render_size.lower().split("x"))
        assert len(size) == 2 and min(size) > 0
    except (ValueError, AssertionError):
        p.error(f"--render-size: expected WIDTHxHEIGHT, got {args.render_size!r}")
    if args.frames < 1 or args.clients < 1 or args.rounds < 1:
        p.error("--frames, --clients and --rounds: expected positive numbers")

    payloads = [frame_arrays(f, 1.0, sensor_units=True) for f in load_dataset(args.data, max_frames=args.frames)]
    h, w = payloads[0]["rgb"].shape[:2]
    print(machine_summary())
    print(f"data: {args.data.name}, {len(payloads)} frames at {w}x{h}, voxel {args.voxel * 1000:g} mm; "
          f"{args.clients} clients rendering {size[0]}x{size[1]}\n")
    quiet, loaded, ratios, refused, load_rows = [], [], [], 0, []
    with tempfile.TemporaryDirectory() as data_dir:
        port = free_port()
        service = start_service(port, Path(data_dir))
        try:
            url = f"http://127.0.0.1:{port}"
            with Client(url) as client:
                rendered = client.create_session(voxel_size=args.voxel)
                for q in payloads:
                    rendered.add_frame(**q)
            stream(url, payloads[:2], args.voxel)  # warm the service's kernels
            for _ in range(args.rounds):
                alone, n = stream(url, payloads, args.voxel)
                before = refusals(url)
                with RenderLoop(url, rendered.id, payloads[0], size, args.clients) as load:
                    if not wait_for(lambda: refusals(url) > before, timeout=300):  # the session's queue is full
                        raise SystemExit(f"{args.clients} render clients never filled the session's queue")
                    before = refusals(url)
                    busy, m = stream(url, payloads, args.voxel)
                    done, refused_renders = load.done, refusals(url) - before - m
                quiet += alone
                loaded += busy
                refused += n + m
                ratios.append(ratio(busy, alone))
                load_rows.append((done, refused_renders))
        finally:
            service.terminate()
            service.wait(timeout=60)

    print_table("Another session's frames, quiet vs during looping large renders (round trips, one client)", [
        {"stream": "quiet", "frames taken": f"{len(quiet)} of {len(payloads) * args.rounds}",
         "ms/frame (med/min/max)": stats_ms(quiet), "": ""},
        {"stream": f"during {args.clients} looping {size[0]}x{size[1]} renders",
         "frames taken": f"{len(loaded)} of {len(payloads) * args.rounds}", "ms/frame (med/min/max)": stats_ms(loaded) if loaded else "-",
         "": f"renders done / refused (429, retried) while streaming: {', '.join(f'{d} / {r}' for d, r in load_rows)}"},
        {"stream": "loaded / quiet median", "frames taken": f"{refused} refused (429)",
         "ms/frame (med/min/max)": ratio(loaded, quiet), "": f"per round: {', '.join(ratios)} (target: within 2x)"},
    ])


if __name__ == "__main__":
    main()
