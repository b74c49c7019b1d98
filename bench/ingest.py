"""Ingest as a user runs it: `canonical serve` plus `canonical stream CAPTURE --voxel-size V` with the
CLI's own defaults; frames/s end to end and the disk a session keeps per frame.

    python bench/ingest.py [--data ../shared/data/realsense_shelf] [--voxel-size 0.004] [--runs 2]
                           [--in-flight 1 3] [--base PATH] [--viewer] [--phone FRAMES]

Each run starts a fresh service (a subprocess, its own temporary data directory), streams the capture
with the CLI (a subprocess: its summary line gives frames/s), samples the session's folder every
20 ms while it runs, then stops the service gracefully (SIGTERM: it snapshots and restarts the log)
and measures the folder again. Before the runs, the client's side in process: what building one
frame's body costs and weighs in each form the SDK sends (`client.sdk.frame_body`), what the
service's decode of it costs (`server.wire.frame_from_message`), and what zstandard over it (the
archive's compression of raw arrays) would cost and gain. Disk per frame counts every file but the scene snapshot
(``scene.snap`` and one being written); the peak while it runs is given without and with the
snapshots. ``--in-flight`` lists the CLI's ``--in-flight`` values to run (same service settings);
``--base`` also runs another checkout of the project (e.g. the tree before a change, its numba cache
warmed), interleaved with this one, so that both see the same load (with ``--viewer``, its viewer
runs too, each tree's judged against its own run without the viewer). ``--phone`` also streams that
many phone-style frames (the shelf's colour enlarged to 1920x1440, its depth at 256x192, as an
iPhone's ARKit gives them) with the SDK into a fresh service, the whole image as PNG (what the SDK
sent before it fitted the colour to the depth) and the SDK's default in turn (``--in-flight`` with no
value skips the `canonical stream` runs). ``--viewer`` also runs the first
``--in-flight`` value twice more with the web viewer open on the session, in headless Debian chromium
(Playwright, as `bench/viewer.py`): once with the page opened as soon as the CLI prints the session's
id, so that the page's loading (a browser tab's start, its scripts, its first picture) falls inside
the stream, and once with the page open before the first frame, as a long stream's viewer is for
nearly all of its frames (the session made with the SDK, its page loaded and subscribed to its
events, then `canonical stream --session ID`: the CLI's clock then starts after the session exists,
a few milliseconds earlier in the stream than with ``--voxel-size``). The page renders each new state
as a user's would; a second table says what the viewer costs:
the CPU of the service's render workers and solves (its threads at nice 15 or lower: a run without
the viewer gives their share without it) and of chromium, and the pictures the page drew. Timings
on a shared machine are noisy: compare the runs of one invocation, and take the best of several;
the CPU time a frame costs the service and the client (user + system, all threads; the client's
includes its start-up) moves less with other work than the wall time does. Never asserts timings.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from statistics import median
from typing import Literal

import numpy as np
import zstandard

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table  # noqa: E402

from canonical_core.datasets import load_tsdf_fusion  # noqa: E402
from client.cli.capture import capture_frames, frame_arrays  # noqa: E402
from client.cli.launch import free_port, wait_until_healthy  # noqa: E402
from client.cli.sessions import viewer_url  # noqa: E402
from client.sdk import encode_png, frame_body, scaled_intrinsics  # noqa: E402
from server.payloads import ZSTD_LEVEL  # noqa: E402
from server.scheduler import RENDER_NICE  # noqa: E402
from server.wire import frame_from_message, unpack  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data" / "realsense_shelf"
SNAPSHOT = re.compile(r"^scene\.snap(\..*)?$")  # the snapshot and one being written (`server.durability`)
SUMMARY = re.compile(r"(\d+) frames in ([\d.]+) s \(([\d.]+) frames/s\)")


def folder_bytes(folder: Path) -> tuple[int, int]:
    """(bytes of every file but the snapshots, bytes of the snapshots) under ``folder``."""
    kept = snaps = 0
    for root, _, files in os.walk(folder):
        for name in files:
            try:
                size = os.stat(os.path.join(root, name)).st_size
            except FileNotFoundError:  # renamed or removed meanwhile (a snapshot's commit)
                continue
            if SNAPSHOT.match(name):
                snaps += size
            else:
                kept += size
    return kept, snaps


class Sampler(threading.Thread):
    """The peak of `folder_bytes` of the sessions' folder, sampled every ``interval`` seconds."""

    def __init__(self, folder: Path, interval: float = 0.02):
        super().__init__(daemon=True)
        self.folder, self.interval, self.stop = folder, interval, threading.Event()
        self.peak_kept = self.peak_all = 0

    def run(self) -> None:
        while not self.stop.is_set():
            kept, snaps = folder_bytes(self.folder)
            self.peak_kept, self.peak_all = max(self.peak_kept, kept), max(self.peak_all, kept + snaps)
            time.sleep(self.interval)


def proc_stat(path: Path) -> tuple[str, list[str], float] | None:
    """(command name, the fields after it, user + system CPU seconds) of a /proc ``.../stat`` file;
    None where its process or thread ended meanwhile."""
    try:
        text = path.read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    name, rest = text.split("(", 1)[1].rsplit(")", 1)
    fields = rest.split()
    return name, fields, (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (all its threads), from /proc."""
    return proc_stat(Path(f"/proc/{pid}/stat"))[2]


def low_priority_cpu(pid: int, nice: int = RENDER_NICE) -> float:
    """CPU seconds so far of the threads of process ``pid`` at OS priority ``nice`` or lower: the
    service's render workers (renders, the viewer's pictures) and its background solves."""
    threads = filter(None, map(proc_stat, Path(f"/proc/{pid}/task").glob("*/stat")))
    return sum(cpu for _, fields, cpu in threads if int(fields[16]) >= nice)


def chromium_cpu() -> float:
    """CPU seconds so far of every chromium process on the machine, from /proc."""
    processes = filter(None, map(proc_stat, Path("/proc").glob("[0-9]*/stat")))
    return sum(cpu for name, _, cpu in processes if "chrom" in name)


Watch = Literal["opened", "waiting"]  # the viewer opened as the stream starts; open before its first frame


def client_seconds() -> float:
    """User + system CPU seconds of this process's waited-for children so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def stream_watched(cmd: list[str], cwd: Path, env: dict, url: str, voxel: float,
                   viewer: Watch) -> tuple[subprocess.CompletedProcess, dict]:
    """Run the `canonical stream` command ``cmd`` (without a session or voxel size: this adds them)
    with the web viewer open on its session in headless chromium: ``viewer`` "opened" opens the page
    when the CLI prints the new session's id (``--voxel-size``), "waiting" makes the session first
    (the SDK) and streams into it (``--session``) once its page is loaded and subscribed to its
    events. Its completed process, and chromium's CPU seconds, the stream client's (not the browser's
    or its driver's) and the pictures the page drew (full and previews) while the stream ran."""
    from playwright.sync_api import sync_playwright
    from viewer import CHROMIUM, CHROMIUM_ARGS

    from client.sdk import Client

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_context(viewport={"width": 900, "height": 520}).new_page()
        if viewer == "waiting":
            with Client(url) as client:
                session_id = client.create_session(voxel_size=voxel).id
            page.goto(viewer_url(url, session_id))
            page.wait_for_function("window.viewer && viewer.info && document.getElementById('live').textContent === 'live'")
            cmd = cmd + ["--session", session_id]
        else:
            cmd = cmd + ["--voxel-size", str(voxel)]
        before, client = chromium_cpu(), client_seconds()
        stream = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        printed = stream.stdout.readline().strip()
        if viewer == "opened" and printed:
            page.goto(viewer_url(url, printed))
        stdout, stderr = stream.communicate()
        client = client_seconds() - client  # the stream's process alone: the browser is not waited for yet
        drawn = page.evaluate("window.viewer ? viewer.history.map((t) => t.full) : []")
        watched = {"chromium_cpu": chromium_cpu() - before, "client_cpu": client, "full": sum(drawn),
                   "previews": len(drawn) - sum(drawn)}
        browser.close()
    return subprocess.CompletedProcess(cmd, stream.returncode, printed + "\n" + stdout, stderr), watched


@contextlib.contextmanager
def running_service(repo: Path, data_dir: Path, threads: int | None = None, sampled=None):
    """`canonical serve` of ``repo`` (``--threads`` when given) on a free port, its data in ``data_dir``,
    once healthy: (url, process, environment); stopped gracefully (SIGTERM: it snapshots) on exit.
    ``sampled(pid)``, where given, is called as soon as the process exists (to watch its start)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CANONICAL_")}
    env["NUMBA_CACHE_DIR"] = str(repo / ".numba_cache")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    service = subprocess.Popen([sys.executable, "-m", "client.cli", "serve", "--port", str(port), "--data-dir",
                                str(data_dir), "--log-level", "warning"] + ([] if threads is None else
                                                                          ["--threads", str(threads)]),
                               cwd=repo, env=env)
    if sampled is not None:
        sampled(service.pid)
    try:
        wait_until_healthy(url, service, timeout=600.0)
        yield url, service, env
    finally:
        service.send_signal(signal.SIGINT if sys.platform == "win32" else signal.SIGTERM)
        service.wait(timeout=120)


def one_run(repo: Path, data: Path, voxel: float, in_flight: int | None, threads: int | None = None,
            viewer: Watch | None = None) -> dict:
    """One service (``--threads`` when given) and one `canonical stream` of ``repo`` (the CLI's
    defaults, ``--in-flight`` when given; with ``viewer``, watched in the web viewer as
    `stream_watched` says); frames/s and disk per frame."""
    with tempfile.TemporaryDirectory() as tmp:
        data_dir = Path(tmp) / "data"
        with running_service(repo, data_dir, threads) as (url, service, env):
            sampler = Sampler(data_dir / "sessions")
            sampler.start()
            cmd = [sys.executable, "-m", "client.cli", "stream", str(data), "--url", url]
            service_cpu, client_cpu = cpu_seconds(service.pid), client_seconds()
            low_cpu = low_priority_cpu(service.pid)
            cmd += [] if in_flight is None else ["--in-flight", str(in_flight)]
            stream, watched = (stream_watched(cmd, repo, env, url, voxel, viewer) if viewer else
                               (subprocess.run(cmd + ["--voxel-size", str(voxel)], cwd=repo, env=env,
                                               capture_output=True, text=True), None))
            service_cpu = cpu_seconds(service.pid) - service_cpu  # before the graceful stop's snapshot
            low_cpu = low_priority_cpu(service.pid) - low_cpu
            client_cpu = watched["client_cpu"] if watched else client_seconds() - client_cpu
            sampler.stop.set()
            sampler.join()
            if stream.returncode != 0:
                raise SystemExit(f"canonical stream failed ({stream.returncode}):\n{stream.stderr[-2000:]}")
            frames, seconds, fps = SUMMARY.search(stream.stderr).groups()
        kept, snaps = folder_bytes(data_dir / "sessions")
        n = int(frames)
        if watched:
            watched["chromium_cpu"] /= n
        return {"frames": n, "seconds": float(seconds), "fps": float(fps), "stopped": kept / n,
                "service_cpu": service_cpu / n, "client_cpu": client_cpu / n, "low_cpu": low_cpu / n,
                "watched": watched, "snapshot": snaps / n, "peak": sampler.peak_kept / n,
                "peak_all": sampler.peak_all / n}


PHONE_COLOUR, PHONE_DEPTH = (1920, 1440), (256, 192)  # an iPhone's ARKit frame: colour and LiDAR depth


def phone_frame(arrays: dict) -> dict:
    """A capture's frame (`frame_arrays`, depth in sensor units) as a phone gives one: the colour
    enlarged to `PHONE_COLOUR` (K to match), the depth (nearest) at `PHONE_DEPTH`, registered to it."""
    from PIL import Image

    h, w = arrays["rgb"].shape[:2]
    return {**arrays, "rgb": np.asarray(Image.fromarray(arrays["rgb"]).resize(PHONE_COLOUR, Image.BILINEAR)),
            "K": scaled_intrinsics(arrays["K"], PHONE_COLOUR[0] / w, PHONE_COLOUR[1] / h),
            "depth": np.asarray(Image.fromarray(arrays["depth"]).resize(PHONE_DEPTH, Image.NEAREST))}


def whole_image(frame: dict) -> dict:
    """A phone-style frame as the SDK sent it before it fitted the colour to the depth: the whole image
    as PNG, for the service to fit (the raw codec sends image bytes untouched; its depth travels
    uncompressed, 0.1 MB, where the SDK's compressed it)."""
    return {**frame, "rgb": encode_png(frame["rgb"]), "codec": "raw"}


def phone_stream(data: Path, voxel: float, frames: int, rounds: int) -> list[dict]:
    """Frames/s of phone-style frames (the capture's, `phone_frame`) streamed with the SDK's `add_frames`
    (3 in flight) into a fresh service, each form of the body in turn, ``rounds`` times; the scene's
    digest of each form (the same frames: the same scene)."""
    from client.sdk import Client

    capture = load_tsdf_fusion(data, max_frames=frames)
    phone = [phone_frame(frame_arrays(capture[i], sensor_units=True)) for i in range(len(capture))]
    forms = {"the whole image as PNG (the SDK before)": whole_image, "fitted to the depth by the SDK (its default)": dict}
    rates: dict[str, list[float]] = {name: [] for name in forms}
    digests: dict[str, set[str]] = {name: set() for name in forms}
    with tempfile.TemporaryDirectory() as tmp, running_service(REPO, Path(tmp) / "data") as (url, _, _), \
            Client(url) as client:
        for _ in range(rounds):
            for name, form in forms.items():
                session = client.create_session(voxel_size=voxel)
                t0 = time.perf_counter()
                for _report in session.add_frames(form(f) for f in phone):
                    pass
                rates[name].append(len(phone) / (time.perf_counter() - t0))
                digests[name].add(session.digest()["sha256"][:12])
                session.delete()
    return [{"body": name, "frames/s (each round)": " / ".join(f"{r:.1f}" for r in runs),
             "frames/s (median)": f"{median(runs):.1f}", "scene digest": ", ".join(sorted(digests[name]))}
            for name, runs in rates.items()]


def body_costs(data: Path, frames: int = 10) -> list[dict]:
    """Per form of a frame's body: ms to build it on the client, ms to decode it on the service, MB."""
    capture = load_tsdf_fusion(data, max_frames=frames)
    arrays = [frame_arrays(capture[i], sensor_units=True) for i in range(len(capture))]
    phone = [phone_frame(a) for a in arrays]
    forms = {"raw arrays (16-bit depth), the SDK before": lambda k: frame_body(**arrays[k], codec="raw"),
             "compact from arrays: PNG colour, zstandard depth (the SDK's default)": lambda k: frame_body(**arrays[k]),
             "the capture's own files (canonical stream's default)": lambda k: frame_body(**files[k]),
             f"phone-style {PHONE_COLOUR[0]}x{PHONE_COLOUR[1]} colour, {PHONE_DEPTH[0]}x{PHONE_DEPTH[1]} depth: "
             "the whole image as PNG (the SDK before)": lambda k: frame_body(**whole_image(phone[k])),
             "phone-style: the colour brought to the depth's pixels by the SDK (its default)":
                 lambda k: frame_body(**phone[k])}
    files = list(capture_frames(capture))
    rows = []
    for name, build in forms.items():
        frame_from_message(unpack(build(0)))  # the decoders' kernels loaded outside the measurement
        t0 = time.perf_counter()
        bodies = [build(k) for k in range(len(capture))]
        built = (time.perf_counter() - t0) * 1000 / len(bodies)
        t0 = time.perf_counter()
        for body in bodies:
            frame_from_message(unpack(body))
        decoded = (time.perf_counter() - t0) * 1000 / len(bodies)
        squeeze = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True)
        t0 = time.perf_counter()
        squeezed = sum(len(squeeze.compress(body)) for body in bodies)
        zstd_ms = (time.perf_counter() - t0) * 1000 / len(bodies)
        rows.append({"body": name, "client builds, ms": f"{built:.1f}", "service decodes, ms": f"{decoded:.1f}",
                     "MB a frame": f"{sum(map(len, bodies)) / len(bodies) / 1e6:.3f}",
                     "the archive's zstandard over it: ms, size": f"{zstd_ms:.1f}, {squeezed / sum(map(len, bodies)):.3f}x"})
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--voxel-size", type=float, default=0.004)
    p.add_argument("--runs", type=int, default=2, help="runs of each configuration (the table gives each and the best)")
    p.add_argument("--in-flight", type=int, nargs="*", default=[3, 1], help="the CLI's --in-flight values to run")
    p.add_argument("--base", type=Path, default=None, help="also run this checkout (its own CLI defaults), interleaved")
    p.add_argument("--threads", type=int, default=None, help="the service's --threads (CPU threads a job; default: all)")
    p.add_argument("--viewer", action="store_true",
                   help="also stream with the web viewer opened on the session as it starts, and open on it "
                        "before its first frame (the first --in-flight value)")
    p.add_argument("--phone", type=int, default=0, metavar="FRAMES",
                   help="also stream this many phone-style frames with the SDK, each body form in turn (--runs rounds)")
    args = p.parse_args(argv)
    configs = [(f"this tree, --in-flight {k}", REPO, k, None) for k in args.in_flight]
    if args.base is not None:
        configs.append((f"base tree {args.base}", args.base.resolve(), None, None))
    if args.viewer:  # each tree's viewer runs, judged against that tree's first run
        watches = (("opened as the stream starts", "opened"), ("open before the first frame", "waiting"))
        trees = [("this tree", REPO)] + ([] if args.base is None else [(f"base tree {args.base}", args.base.resolve())])
        configs += [(f"{tree}, --in-flight {args.in_flight[0]}, viewer {what}", repo, args.in_flight[0], viewer)
                    for tree, repo in trees for what, viewer in watches]
    print(machine_summary())
    print(f"data: {args.data}, voxel {args.voxel_size * 1000:g} mm, {args.runs} runs each, interleaved, service "
          f"--threads {args.threads or 'default'}\n")
    print_table("A frame's body: built by the client, decoded by the service (in process, 10 frames, means)",
                body_costs(args.data))
    if args.phone:
        print_table(f"Phone-style frames ({args.phone} of the shelf's at {PHONE_COLOUR[0]}x{PHONE_COLOUR[1]} with "
                    f"{PHONE_DEPTH[0]}x{PHONE_DEPTH[1]} depth) streamed by the SDK, 3 in flight, into one service",
                    phone_stream(args.data, args.voxel_size, args.phone, args.runs))
    if not configs:
        return
    results: dict[str, list[dict]] = {name: [] for name, *_ in configs}
    for _ in range(args.runs):
        for name, repo, in_flight, viewer in configs:
            results[name].append(one_run(repo, args.data, args.voxel_size, in_flight, args.threads, viewer))
    mb = lambda x: f"{x / 1e6:.3f}"  # noqa: E731
    print_table("`canonical stream` end to end, and disk per frame (MB = 10^6 bytes)", [
        {"configuration": name, "frames": runs[0]["frames"],
         "frames/s (each run)": " / ".join(f"{r['fps']:.1f}" for r in runs),
         "frames/s (best)": f"{max(r['fps'] for r in runs):.1f}",
         "CPU ms a frame, service / client (best)": f"{min(r['service_cpu'] for r in runs) * 1000:.0f} / "
                                                    f"{min(r['client_cpu'] for r in runs) * 1000:.0f}",
         "MB/frame after a graceful stop, no snapshot": mb(min(r["stopped"] for r in runs)),
         "peak MB/frame while running, no snapshot": mb(max(r["peak"] for r in runs)),
         "peak MB/frame while running, with snapshots": mb(max(r["peak_all"] for r in runs)),
         "snapshot MB/frame": mb(runs[0]["snapshot"])}
        for name, runs in results.items()])
    if args.viewer:
        print_table("Where the viewer's cost goes (medians over the runs; CPU ms a frame while the stream ran)", [
            {"configuration": name,
             "service, render workers and solves (nice >= 15)": f"{median(r['low_cpu'] for r in runs) * 1000:.1f}",
             "chromium, all processes": (f"{median(r['watched']['chromium_cpu'] for r in runs) * 1000:.1f}"
                                         if runs[0]["watched"] else "–"),
             "pictures drawn, full / previews": (f"{median(r['watched']['full'] for r in runs):g} / "
                                                 f"{median(r['watched']['previews'] for r in runs):g}"
                                                 if runs[0]["watched"] else "–")}
            for name, runs in results.items()])
    best = {name: max(r["fps"] for r in runs) for name, runs in results.items()}
    # a viewer's run against its own tree's first run; the base tree's first against this tree's
    quiet = {repo: name for name, repo, _, viewer in reversed(configs) if viewer is None}
    against = {name: quiet[repo] if name != quiet[repo] else configs[0][0] for name, repo, _, _ in configs}
    print_table("best frames/s against another run (same invocation)", [
        {"configuration": name, "against": ref, "ratio": f"{best[name] / best[ref]:.2f}"}
        for name, ref in against.items() if name != ref])

if __name__ == "__main__":
    main()
