"""Cluster benchmark: single-process against Ray Serve cluster mode, restore cost, a capacity model,
and a queueing simulation that sizes a fleet from the measured service times.

    python bench/cluster.py [--data ../shared/data/realsense_shelf] [--long ../shared/data/hololens_office]
                            [--sessions 1,4,16] [--frames 6] [--renders 3] [--robots 1000] [--fps 5]

1. Streaming: N concurrent sessions each stream ``--frames`` 640x480 frames and then render
   ``--renders`` 640x480 views, through the single-process service (uvicorn) and through the cluster
   (a local Ray cluster, 1 and 2 owner processes). Frames/s over all sessions, fold and render
   latency (client side) p50/p95.
2. Restore: a 50-frame and a 187-frame session, restored by a fresh owner from its log alone (every
   frame replayed) and from a snapshot.
3. Capacity model (measured): CPU ms per 640x480 fold (process time, one thread), the request's own
   CPU overhead through the cluster, bytes per frame in the log, scene memory per session, restore ms.
4. Queueing simulation (`simulate`): ``--robots`` robots each streaming ``--fps`` frames/s for
   ``--hours``, sessions hashed onto owners as the cluster does, each node ``--cores`` cores serving
   folds drawn from the measured fold times; a session's next frame waits for its previous one (the
   client awaits each acknowledgement). Prints, per node count, the offered load and frame latency
   (capture to acknowledgement) p50/p95/p99 on the most loaded node, up to the fewest nodes whose
   p95 frame waits less than one frame period for a core.

Prints tables and the machine; never asserts timings. Needs the [cluster] extra for part 1.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import secrets
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table  # noqa: E402

from canonical_core import SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service, unclaimed_port  # noqa: E402
from client.sdk import Client, encode_array, pack  # noqa: E402
from server.store import configure_thread  # noqa: E402

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pct(values, q: float) -> float:
    return float(np.percentile(np.asarray(values, np.float64), q)) if len(values) else float("nan")


# -- 1. streaming -----------------------------------------------------------------------------------
def stream_sessions(url: str, payloads: list[dict], sessions: int, renders: int, voxel: float) -> dict:
    """``sessions`` clients at once, each: create, stream ``payloads``, render ``renders`` views."""
    fold_ms, render_ms, errors = [], [], []
    lock = threading.Lock()

    def one():
        try:
            with Client(url, max_retries=64) as client:
                session = client.create_session(voxel_size=voxel)
                for p in payloads:
                    t0 = time.perf_counter()
                    session.add_frame(**{k: v for k, v in p.items() if k != "frame_id"})
                    with lock:
                        fold_ms.append((time.perf_counter() - t0) * 1000)
                for p in payloads[:renders]:
                    t0 = time.perf_counter()
                    session.render_png(p["K"], p["c2w"], p["rgb"].shape[1], p["rgb"].shape[0])
                    with lock:
                        render_ms.append((time.perf_counter() - t0) * 1000)
        except Exception as exc:  # reported in the table
            errors.append(repr(exc))

    threads = [threading.Thread(target=one) for _ in range(sessions)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"frames/s": f"{len(fold_ms) / wall:.2f}", "fold p50/p95 ms": f"{pct(fold_ms, 50):.0f} / {pct(fold_ms, 95):.0f}",
            "render p50/p95 ms": f"{pct(render_ms, 50):.0f} / {pct(render_ms, 95):.0f}", "errors": len(errors)}


def warm(url: str, payload: dict, voxel: float, sessions: int) -> None:
    """Fold and render once in ``sessions`` throwaway sessions, so no timed request pays a first call."""
    with Client(url, max_retries=64) as client:
        for _ in range(sessions):
            session = client.create_session(voxel_size=voxel)
            session.add_frame(**payload)
            session.render_png(payload["K"], payload["c2w"], payload["rgb"].shape[1], payload["rgb"].shape[0])


def bench_streaming(payloads, counts, renders, voxel, threads) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        proc = start_service(port, Path(tmp) / "single")
        try:
            warm(f"http://127.0.0.1:{port}", payloads[0], voxel, 1)
            for n in counts:
                rows.append({"mode": "single process", "sessions": n,
                             **stream_sessions(f"http://127.0.0.1:{port}", payloads, n, renders, voxel)})
        finally:
            proc.terminate()
            proc.wait()
        try:
            import ray
            from ray import serve

            from server.cluster import serve as cluster
            from server.cluster.settings import ClusterSettings
        except ImportError:
            print("(cluster rows skipped: install the [cluster] extra)\n")
            return rows
        cluster.connect(num_cpus=2)
        port = unclaimed_port()  # Serve's proxy keeps the port it started on; Ray's processes take ephemeral ones
        try:
            for owners in (1, 2):
                # owner_cpus unset: fitted to the 2 CPUs (a claim is bookkeeping, not a limit on cores used)
                settings = ClusterSettings(data_dir=Path(tmp) / f"cluster{owners}", owners=owners,
                                           ingress_cpus=0.25, ingress_min_replicas=1, ingress_max_replicas=2,
                                           host="127.0.0.1", port=port, threads=threads,
                                           namespace=f"bench-{owners}")
                cluster.start(settings)
                url = f"http://127.0.0.1:{settings.port}"
                warm(url, payloads[0], voxel, owners * 3)  # start every owner (and its kernels) before timing
                for n in counts:
                    rows.append({"mode": f"cluster, {owners} owner{'s' * (owners > 1)}", "sessions": n,
                                 **stream_sessions(url, payloads, n, renders, voxel)})
                serve.delete(cluster.APP_NAME)
                for k in range(owners):
                    ray.kill(ray.get_actor(cluster.owner_name(k), namespace=settings.namespace))
        finally:
            serve.shutdown()
            ray.shutdown()
    return rows


# -- 2. restore -----------------------------------------------------------------------------------
def message(kwargs: dict) -> bytes:
    msg = {"rgb": encode_array(kwargs["rgb"]), "K": kwargs["K"].tolist(), "c2w": kwargs["c2w"].tolist(),
           "depth": encode_array(kwargs["depth"].astype(np.float32))}
    return pack(msg)


def bench_restore(name: str, frames, voxel: float) -> tuple[list[dict], dict]:
    """Restore ms of one session of ``frames`` (from its log alone, then from a snapshot), and figures
    for the capacity model."""
    from server import wire
    from server.cluster.owner import OwnerStore

    rows, figures = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        store = OwnerStore(tmp, 8, None, 0, 1)
        store.open()
        session = store.create(SceneConfig(voxel_size=voxel))
        payload_bytes, cpu_ms = [], []
        for kwargs in frames:
            payload = message(kwargs)
            payload_bytes.append(len(payload))
            frame = wire.frame_from_message(wire.unpack(payload))
            t0 = time.process_time()
            session.add_frame(payload, frame, snapshot_every_frames=10**9, snapshot_every_seconds=1e9)
            cpu_ms.append((time.process_time() - t0) * 1000)
        figures.update(payload_bytes=float(np.mean(payload_bytes)), memory_bytes=session.scene.memory_bytes(),
                       fold_cpu_ms=cpu_ms, log_bytes=(session.path / "frames.log").stat().st_size)
        holder, stores = session, [store]
        for source in ("log replay", "snapshot"):
            if source == "snapshot":  # written by the current owner (the lease moved with each restore)
                holder.snapshot()
                figures["snapshot_bytes"] = (session.path / "scene.snap").stat().st_size
            stores.append(OwnerStore(tmp, 8, None, 0, 1))
            t0 = time.perf_counter()
            holder = stores[-1].get(session.id)
            ms = (time.perf_counter() - t0) * 1000
            assert holder.scene.digest() == session.scene.digest()
            rows.append({"session": name, "frames": len(frames), "restored from": source, "ms": f"{ms:.0f}",
                         "ms per frame": f"{ms / len(frames):.1f}"})
            figures[f"restore_ms_{source.split()[0]}"] = ms
        stores[-1].close()
    return rows, figures


# -- 4. queueing simulation ---------------------------------------------------------------------------
def simulate(robots: int, fps: float, seconds: float, cores: int, service_ms: np.ndarray, overhead_ms: float,
             rng: np.random.Generator) -> dict:
    """One node serving ``robots`` sessions: frames arrive every 1/fps s per robot (random phase, 5%
    jitter); ``cores`` servers take the oldest ready frame; a session's frame is ready only after its
    previous one was acknowledged. Returns frame latency percentiles (ms, capture to acknowledgement)."""
    period = 1.0 / fps
    heap: list[tuple[float, int, int]] = []  # (time, kind: 0 arrival / 1 acknowledged, robot)
    for r in range(robots):
        heapq.heappush(heap, (rng.uniform(0, period), 0, r))
    backlog = [deque() for _ in range(robots)]  # capture times not yet sent (the robot awaits its previous ack)
    sending = [False] * robots  # a frame of this robot is queued or being folded
    ready: deque[int] = deque()  # robots whose next frame waits for a core, oldest first
    free, latencies = cores, []
    while heap:
        now, kind, r = heapq.heappop(heap)
        if kind == 0:
            if now < seconds:
                heapq.heappush(heap, (now + period * rng.uniform(0.95, 1.05), 0, r))
                backlog[r].append(now)
        else:
            free += 1
            sending[r] = False
            latencies.append((now - backlog[r].popleft()) * 1000)
        if not sending[r] and backlog[r]:
            sending[r] = True
            ready.append(r)
        while free and ready:
            service = (service_ms[rng.integers(len(service_ms))] + overhead_ms) / 1000
            free -= 1
            heapq.heappush(heap, (now + service, 1, ready.popleft()))
    lat = np.asarray(latencies)
    return {"p50": pct(lat, 50), "p95": pct(lat, 95), "p99": pct(lat, 99),
            "frames": len(lat)}


def size_fleet(robots: int, fps: float, seconds: float, cores: int, service_ms, overhead_ms,
               owners_per_node: int) -> list[dict]:
    """For each node count from the one that 100% utilisation would need: sessions hashed onto
    ``owners_per_node`` owners per node as the cluster does (Ray spreads owners evenly by their
    declared CPUs); simulate the most loaded node. A count suffices when the 95th-percentile
    frame waits less than one frame period for a core (latency p95 <= period + service p95); it stops
    at the first that does."""
    from server.cluster.owner import shard_of

    rng = np.random.default_rng(0)
    ids = [secrets.token_hex(16) for _ in range(robots)]
    service = np.asarray(service_ms) + overhead_ms
    need = robots * fps * float(service.mean()) / 1000 / cores  # nodes at 100% utilisation
    bound = 1000 / fps + float(np.percentile(service, 95))
    rows = []
    first = max(1, int(np.floor(need)))
    for nodes in range(first, max(first + 50, int(4 * need) + 1)):
        load = np.bincount([shard_of(i, nodes * owners_per_node) // owners_per_node for i in ids], minlength=nodes)
        busiest = int(load.max())
        result = simulate(busiest, fps, seconds, cores, service_ms, overhead_ms, rng)
        ok = result["p95"] <= bound
        offered = busiest * fps * float(service.mean()) / 1000 / cores
        rows.append({"nodes": nodes, "robots on busiest node": busiest, "its offered load": f"{offered:.2f}",
                     "latency p50/p95/p99 ms": f"{result['p50']:.0f} / {result['p95']:.0f} / {result['p99']:.0f}",
                     f"p95 <= {bound:.0f} ms": "yes" if ok else "no"})
        if ok:
            break
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(SHARED / "realsense_shelf"))
    ap.add_argument("--long", default=str(SHARED / "hololens_office"), help="the long session to restore ('' skips it)")
    ap.add_argument("--voxel", type=float, default=0.008)
    ap.add_argument("--sessions", default="1,4,16")
    ap.add_argument("--frames", type=int, default=6, help="frames each session streams in part 1")
    ap.add_argument("--renders", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--robots", type=int, default=1000)
    ap.add_argument("--fps", type=float, default=5.0)
    ap.add_argument("--cores", type=int, default=16, help="cores per node in the simulation")
    ap.add_argument("--owners-per-node", type=int, default=4, help="owners per node in the simulation (more even load)")
    ap.add_argument("--sim-seconds", type=float, default=600.0,
                    help="simulated time per node count (the arrival process is stationary: an hour behaves as this)")
    ap.add_argument("--skip-streaming", action="store_true")
    args = ap.parse_args()
    os.environ["CANONICAL_THREADS"] = str(args.threads)  # the single-process service started below, too
    configure_thread(args.threads)
    torch.set_num_threads(args.threads)
    print(machine_summary())

    shelf = list(load_dataset(Path(args.data)))
    payloads = [frame_arrays(f, 1.0) for f in shelf[: args.frames]]
    if not args.skip_streaming:
        rows = bench_streaming(payloads, [int(x) for x in args.sessions.split(",")], args.renders, args.voxel, args.threads)
        print_table(f"Streaming: {args.frames} frames of 640x480 per session, then {args.renders} renders", rows)
        streaming = rows
    else:
        streaming = []

    restore_rows, figures = bench_restore("realsense_shelf", [frame_arrays(f, 1.0) for f in shelf], args.voxel)
    rows, long_figures = [], {}
    if args.long:
        long_frames = list(load_dataset(Path(args.long)))
        rows, long_figures = bench_restore(Path(args.long).name, [frame_arrays(f, 1.0) for f in long_frames], args.voxel)
    print_table("Restore by a fresh owner", restore_rows + rows)

    def both(key: str, scale: float = 1.0) -> str:
        long = f"{long_figures[key] / scale:.1f}" if key in long_figures else "-"
        return f"{figures[key] / scale:.1f} / {long}"

    fold_ms = np.asarray(figures["fold_cpu_ms"][1:])  # the first fold pays for nothing the rest do not, but skip it
    overhead = request_overhead_ms(streaming, float(np.median(fold_ms)))
    hour_frames = args.fps * 3600
    sizes = f"{len(shelf)} / {len(long_figures.get('fold_cpu_ms', [])) or '-'} frames"
    model = [
        {"quantity": "CPU ms per 640x480 fold (log + fold, one thread), p50 / p95",
         "value": f"{np.median(fold_ms):.1f} / {np.percentile(fold_ms, 95):.1f}"},
        {"quantity": "request cost beyond the fold, ms: HTTP, decode, fsync, forwarding (cluster fold p50 over HTTP, "
                     "1 session, minus the in-process fold p50; wall time, so an upper bound on its CPU)",
         "value": f"{overhead:.1f}"},
        {"quantity": "bytes per frame in the log (msgpack: raw rgb + float32 depth)", "value": f"{figures['payload_bytes']:.0f}"},
        {"quantity": f"log bytes per session-hour at {args.fps:g} fps (between snapshots)",
         "value": f"{figures['payload_bytes'] * hour_frames / 1e9:.1f} GB"},
        {"quantity": f"scene memory per session, MB, {sizes}", "value": both("memory_bytes", 1e6)},
        {"quantity": f"snapshot, MB, {sizes}", "value": both("snapshot_bytes", 1e6)},
        {"quantity": f"restore ms from a snapshot, {sizes}", "value": both("restore_ms_snapshot")},
        {"quantity": f"restore ms by log replay, {sizes}", "value": both("restore_ms_log")},
    ]
    print_table("Capacity model (measured here)", model)

    service = fold_ms  # 640x480 folds; a session's folds get slower as its scene grows (see the restore rows)
    if 1000 / (float(service.mean()) + overhead) < args.fps:
        print(f"note: one session folds at most {1000 / (float(service.mean()) + overhead):.1f} frames/s one after another; "
              f"at {args.fps:g} fps a client must send before the previous acknowledgement\n")
    rows = size_fleet(args.robots, args.fps, args.sim_seconds, args.cores, service, overhead, args.owners_per_node)
    print_table(f"Queueing simulation: {args.robots} robots at {args.fps:g} fps, {args.cores}-core nodes with "
                f"{args.owners_per_node} owners each, service = "
                f"the {len(service)} measured 640x480 fold CPU times + {overhead:.1f} ms request overhead", rows)
    print(json.dumps({"nodes": rows[-1]["nodes"] if rows else None}))
    return 0


def request_overhead_ms(streaming: list[dict], fold_ms: float) -> float:
    """Client-side fold p50 through the cluster with one session, minus the in-process fold p50 (0 when
    the streaming part did not run)."""
    for row in streaming:
        if row["mode"].startswith("cluster") and row["sessions"] == 1:
            return max(0.0, float(row["fold p50/p95 ms"].split(" / ")[0]) - fold_ms)
    return 0.0


if __name__ == "__main__":
    sys.exit(main())
