"""Service benchmark: frames/s over HTTP vs in-process fold, render latency under 4 clients, and
fold latency while a viewer renders (a plain session and one with the colour solve).

    python bench/service.py [--data ../shared/data/realsense_shelf] [--frames 30] [--renders 40] [--solve-views 16]
                            [--snapshot-every 10]

Starts the real service (`canonical serve`, uvicorn) on a free loopback port with a temporary data
directory, streams the same frames through the Python client that it folds in-process, and prints
tables with medians and the machine. Beside them, the HTTP floor: the same request bodies POSTed to a
bare FastAPI route that only reads them (`ECHO_SERVER`), what any fold over HTTP pays on this
machine. The service snapshots a session every ``--snapshot-every`` frames (its
`snapshot_every_frames`), and the first table splits out the round trips of the frames that made a
snapshot due. Never asserts timings.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, stats_ms, time_each  # noqa: E402

from canonical_core import SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.scene import Scene  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service, wait_until_healthy  # noqa: E402
from client.sdk import Client, frame_body  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def in_process(frames, voxel: float) -> list[float]:
    return time_each(Scene(SceneConfig(voxel_size=voxel)).fold, frames)


def over_http(url: str, payloads: list[dict], voxel: float) -> tuple[list[float], list[float], str]:
    """Client-side round trip ms and the server's own fold ms per frame."""
    with Client(url) as client:
        session = client.create_session(voxel_size=voxel)
        total, server = [], []
        for p in payloads:
            t0 = time.perf_counter()
            report = session.add_frame(**p)
            total.append((time.perf_counter() - t0) * 1000)
            server.append(report["ms"])
        return total, server, session.id


# The HTTP floor: a bare FastAPI route under uvicorn (h11, as the service) that reads the body and answers
# with its length, in a child process. What a POST of a frame's body costs on this machine before any work.
ECHO_SERVER = """
import sys, uvicorn
from fastapi import FastAPI, Request
app = FastAPI()
@app.get("/healthz")
async def healthz():
    return {}
@app.post("/echo")
async def echo(request: Request):
    return {"bytes": len(await request.body())}
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning", http="h11")
"""


def echo_round_trips(bodies: list[bytes]) -> list[float]:
    """ms to POST each body (the SDK's client, httpx) to `ECHO_SERVER` and read its answer."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", ECHO_SERVER, str(port)])
    try:
        wait_until_healthy(f"http://127.0.0.1:{port}", proc, timeout=60.0)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as client:
            out = []
            for body in bodies:
                t0 = time.perf_counter()
                client.post("/echo", content=body, headers={"Content-Type": "application/msgpack"}).json()
                out.append((time.perf_counter() - t0) * 1000)
            return out
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def snapshot_split(round_trips: list[float], every: int) -> list[tuple[str, list[float]]]:
    """The round trips of the frames that made a snapshot due (the scene then held a multiple of
    ``every`` frames) and of the others."""
    due = [ms for k, ms in enumerate(round_trips) if (k + 1) % every == 0]
    other = [ms for k, ms in enumerate(round_trips) if (k + 1) % every]
    return [(f"made a snapshot due (every {every})", due), ("did not", other)]


def render_latency(url: str, session_id: str, cameras, clients: int, per_client: int) -> list[float]:
    lat: list[float] = []
    lock = threading.Lock()

    def worker(k: int) -> None:
        with Client(url) as client:
            session = client.session(session_id)
            for j in range(per_client):
                cam = cameras[(k * per_client + j) % len(cameras)]
                t0 = time.perf_counter()
                session.render(cam.K64(), cam.c2w64(), cam.width, cam.height)
                with lock:
                    lat.append((time.perf_counter() - t0) * 1000)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return lat


def fold_while_viewing(url: str, payloads: list[dict], voxel: float, settings: dict) -> tuple[list[float], list[float]]:
    """A new session; one client folds ``payloads`` while another renders the first frame's view in a
    loop, as a live viewer would. Returns the fold round trips and the render round trips (ms)."""
    folds, renders, stop = [], [], threading.Event()
    K, c2w, rgb = payloads[0]["K"], payloads[0]["c2w"], payloads[0]["rgb"]
    with Client(url) as client:
        session = client.create_session(voxel_size=voxel, **settings)
        session.add_frame(**payloads[0])

        def viewer() -> None:
            with Client(url) as own:
                mine = own.session(session.id)
                while not stop.is_set():
                    t0 = time.perf_counter()
                    mine.render(K, c2w, rgb.shape[1], rgb.shape[0])
                    renders.append((time.perf_counter() - t0) * 1000)

        thread = threading.Thread(target=viewer)
        thread.start()
        try:
            for p in payloads[1:]:
                t0 = time.perf_counter()
                session.add_frame(**p)
                folds.append((time.perf_counter() - t0) * 1000)
        finally:
            stop.set()
            thread.join()
        session.delete()
    return folds, renders


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--voxel", type=float, default=0.004)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--renders", type=int, default=40, help="renders in total across the 4 clients")
    p.add_argument("--scale", type=float, default=1.0, help="also resize frames (e.g. 0.5 for 320x240)")
    p.add_argument("--solve-views", type=int, default=16, help="colour_solve.views of the viewed session (0: skip that table)")
    p.add_argument("--snapshot-every", type=int, default=10, help="the service's snapshot_every_frames")
    args = p.parse_args(argv)
    if args.snapshot_every < 1:
        p.error("--snapshot-every: expected a positive number of frames")
    if args.solve_views < 0:
        p.error("--solve-views: expected a non-negative number of kept views")

    frames = list(load_dataset(args.data, max_frames=args.frames))
    # depth travels in the sensor's 16-bit units, as a depth camera's client sends it
    payloads = [frame_arrays(f, args.scale, sensor_units=True) for f in frames]
    if args.scale != 1.0:  # fold the same resized frames in-process that travel over HTTP
        from canonical_core import Camera, Frame

        frames = [Frame(rgb=p_["rgb"], camera=Camera(p_["K"], p_["c2w"], p_["rgb"].shape[1], p_["rgb"].shape[0]),
                        depth=p_["depth"]) for p_ in (frame_arrays(f, args.scale) for f in frames)]
    print(machine_summary())
    print(f"data: {args.data.name}, {len(frames)} frames at {frames[0].width}x{frames[0].height}, voxel {args.voxel * 1000:g} mm\n")
    in_process(frames[:2], args.voxel)  # compile / load kernels outside the measurement
    local = in_process(frames, args.voxel)
    bodies = [frame_body(**p_) for p_ in payloads]
    echo = echo_round_trips(bodies[:2] + bodies)[2:]  # the first two warm the connection

    with tempfile.TemporaryDirectory() as data_dir:
        port = free_port()
        os.environ["CANONICAL_SNAPSHOT_EVERY_FRAMES"] = str(args.snapshot_every)  # the service's setting
        service = start_service(port, Path(data_dir))
        try:
            url = f"http://127.0.0.1:{port}"
            over_http(url, payloads[:2], args.voxel)  # warm the service's kernels
            total, server, sid = over_http(url, payloads, args.voxel)
            cams = [f.camera for f in frames]
            render_latency(url, sid, cams[:2], clients=1, per_client=2)  # warm decode cache and renderer
            lat = render_latency(url, sid, cams, clients=4, per_client=max(1, args.renders // 4))
            viewed = {"plain session": {}}
            if args.solve_views:
                viewed[f"colour_solve.views {args.solve_views}"] = {"colour_solve": {"views": args.solve_views}}
            viewed = {name: fold_while_viewing(url, payloads, args.voxel, settings) for name, settings in viewed.items()}
        finally:
            service.terminate()
            service.wait(timeout=60)

    fps_local = 1000 / statistics.median(local)
    fps_http = 1000 / statistics.median(total)
    print_table("Fold: in-process vs over HTTP (same frames, same order)", [
        {"path": "in-process Scene.fold", "ms/frame (med/min/max)": stats_ms(local), "frames/s (median)": f"{fps_local:.1f}"},
        {"path": "HTTP round trip (client)", "ms/frame (med/min/max)": stats_ms(total), "frames/s (median)": f"{fps_http:.1f}"},
        {"path": "  of which server fold", "ms/frame (med/min/max)": stats_ms(server), "frames/s (median)": ""},
        {"path": "overhead ratio HTTP / in-process", "ms/frame (med/min/max)": f"{statistics.median(total) / statistics.median(local):.2f}",
         "frames/s (median)": ""},
        {"path": f"the HTTP floor: the same {statistics.median(map(len, bodies)) / 1e6:.2f} MB bodies to a bare FastAPI echo route",
         "ms/frame (med/min/max)": stats_ms(echo), "frames/s (median)": ""},
        {"path": "  floor + in-process fold, over in-process", "ms/frame (med/min/max)":
         f"{(statistics.median(echo) + statistics.median(local)) / statistics.median(local):.2f}", "frames/s (median)": ""},
        *({"path": f"  round trips of the frames that {label}", "ms/frame (med/min/max)": stats_ms(ms), "frames/s (median)": ""}
          for label, ms in snapshot_split(total, args.snapshot_every) if ms),
    ])
    lat = np.asarray(lat)
    print_table(f"Render latency, 4 concurrent clients, {frames[0].width}x{frames[0].height}, {len(lat)} renders", [
        {"p50 ms": f"{np.percentile(lat, 50):.0f}", "p99 ms": f"{np.percentile(lat, 99):.0f}", "max ms": f"{lat.max():.0f}"}])
    print_table(f"Folds while a viewer renders in a loop ({len(payloads) - 1} folds, one client each)", [
        {"session": name, "fold ms (med/min/max)": stats_ms(folds), "fold p95 ms": f"{np.percentile(folds, 95):.0f}",
         "renders": len(renders), "render ms (med/min/max)": stats_ms(renders) if renders else "-"}
        for name, (folds, renders) in viewed.items()])


if __name__ == "__main__":
    main()
