"""Web viewer benchmark: time to first image and images/s while dragging, at 512x384 on the shelf.

    python bench/viewer.py [--data ../shared/data/realsense_shelf] [--voxel 0.004] [--drag-s 8]

Starts the real service, streams the capture (about 150k Gaussians at 4 mm), then drives the viewer
page in Debian's chromium (Playwright, as the browser tests do): the time from opening the page to
its first full image, and a scripted drag (pointer moves every 16 ms) during which it counts the
images the page draws. The page's own per-image timings give the breakdown: server render (queue +
rasterise), picture (colour mapping), encode, transfer (round trip minus server time) and decode in
the browser. A second table times the image route over plain HTTP per size and format. Never
asserts timings; the machine is shared, so its load is printed with the tables.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service  # noqa: E402
from client.sdk import Client  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
PREVIEW_GAUSSIANS = 60000  # the viewer's level of detail while the pose moves (view.js)
FULL = "window.viewer && window.viewer.drawn.full && window.viewer.drawn.version === window.viewer.version"


def med(values) -> str:
    values = [v for v in values if v is not None]
    return f"{statistics.median(values):.1f}" if values else "–"


def breakdown(name: str, timings: list[dict], seconds: float | None = None) -> dict:
    row = {"what": name, "images": len(timings), "images/s": f"{len(timings) / seconds:.1f}" if seconds else "–"}
    server = [t.get("render", 0) + t.get("picture", 0) + t.get("encode", 0) for t in timings]
    row.update({
        "render ms": med(t.get("render") for t in timings), "picture ms": med(t.get("picture") for t in timings),
        "encode ms": med(t.get("encode") for t in timings),
        "transfer ms": med(t["fetch"] - s for t, s in zip(timings, server)),
        "decode ms": med(t["decode"] for t in timings), "round trip ms": med(t["fetch"] for t in timings),
        "KiB": med(t["bytes"] / 1024 for t in timings),
    })
    return row


def browse(url: str, session_id: str, drag_s: float, shots: Path | None) -> tuple[float, list[dict], list[dict], float]:
    """(seconds to the first full image, its timings, the drag's preview timings, drag seconds);
    with ``shots``, screenshots of the first image in RGB and depth mode go there."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_context(viewport={"width": 900, "height": 520}).new_page()
        t0 = time.perf_counter()
        page.goto(f"{url}/sessions/{session_id}/view")
        page.wait_for_function(FULL, timeout=120_000)
        first = time.perf_counter() - t0
        first_timing = page.evaluate("viewer.history")
        box = page.locator("#stage").bounding_box()
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        if shots:  # step back and turn a little, so that the input cameras' frustums are in view
            version = page.evaluate("viewer.version")
            page.mouse.move(x, y)
            page.mouse.wheel(0, 250)
            page.mouse.down()
            page.mouse.move(x + 90, y - 10, steps=5)
            page.mouse.up()
            page.wait_for_function(f"{FULL} && viewer.version > {version}", timeout=120_000)
            page.screenshot(path=shots / "viewer_rgb.png")
            version = page.evaluate("viewer.version")
            page.select_option("#mode", "depth")
            page.wait_for_function(f"{FULL} && viewer.version > {version}", timeout=120_000)
            page.screenshot(path=shots / "viewer_depth.png")
            page.select_option("#mode", "rgb")
            version = page.evaluate("viewer.version")
            page.click("#latest")  # the drag starts where a first visit does: at the latest input camera
            page.wait_for_function(f"{FULL} && viewer.version > {version}", timeout=120_000)
        page.mouse.move(x, y)
        page.mouse.down()
        start = page.evaluate("performance.now()")
        t_end, k = time.perf_counter() + drag_s, 0
        while time.perf_counter() < t_end:  # a slow circle, one move per 16 ms
            k += 1
            page.mouse.move(x + 120 * np.sin(k / 40), y + 60 * np.sin(k / 25))
            page.wait_for_timeout(16)
        end = page.evaluate("performance.now()")
        page.mouse.up()
        drag = page.evaluate(f"viewer.history.filter(t => t.at >= {start} && t.at <= {end} && !t.full)")
        browser.close()
    return first, first_timing, drag, (end - start) / 1000


def http_rows(url: str, session_id: str, camera, repeats: int) -> list[dict]:
    K, c2w = camera
    rows = []
    http = httpx.Client(timeout=120)  # one keep-alive connection, as the browser holds
    for w, h, fmt, lod in ((512, 384, "png", None), (512, 384, "jpeg", None), (512, 384, "webp", None),
                           (256, 192, "jpeg", None), (256, 192, "jpeg", PREVIEW_GAUSSIANS)):
        s = w / 640
        params = {"pose": ",".join(map(str, np.asarray(c2w).ravel())), "width": w, "height": h, "format": fmt,
                  "K": f"{K[0][0] * s},{K[1][1] * s},{K[0][2] * s},{K[1][2] * s}", "quality": 70}
        if lod:
            params["max_gaussians"] = lod
        timings = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            r = http.get(f"{url}/v1/sessions/{session_id}/image", params=params)
            r.raise_for_status()
            total = (time.perf_counter() - t0) * 1000
            parts = dict(p.strip().split(";dur=") for p in r.headers["server-timing"].split(","))
            timings.append({**{k: float(v) for k, v in parts.items()}, "fetch": total, "decode": 0.0, "bytes": len(r.content)})
        row = breakdown(f"HTTP {w}x{h} {fmt}" + (f", {lod // 1000}k Gaussians" if lod else ""), timings)
        row.pop("decode ms")
        row["images/s"] = f"{1000 / statistics.median(t['fetch'] for t in timings):.1f}"
        rows.append(row)
    http.close()
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--voxel", type=float, default=0.004)
    ap.add_argument("--max-frames", type=int, default=50)
    ap.add_argument("--drag-s", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=8)
    ap.add_argument("--screenshots", type=Path, default=None, help="save the page in RGB and depth mode here")
    args = ap.parse_args()
    frames = list(load_dataset(args.data, max_frames=args.max_frames))
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        proc = start_service(port, Path(tmp))
        url = f"http://127.0.0.1:{port}"
        try:
            with Client(url) as client:
                session = client.create_session(voxel_size=args.voxel)
                for frame in frames:
                    session.add_frame(**frame_arrays(frame))
                gaussians = session.stats()["gaussians"]
            first, first_timing, drag, drag_s = browse(url, session.id, args.drag_s, args.screenshots)
            last = frames[-1].camera
            rows = http_rows(url, session.id, (last.K64(), last.c2w64()), args.repeats)
        finally:
            proc.terminate()
            proc.wait(60)
    print(machine_summary())
    print(f"scene: {Path(args.data).name}, {len(frames)} frames, voxel {args.voxel} m, {gaussians} Gaussians; "
          f"time to first image (page open -> first full 512x384 PNG drawn): {first:.2f} s\n")
    print_table(f"viewer in chromium: first image (full PNG) and dragging (previews: 256x192 JPEG q70 of the best "
                f"{PREVIEW_GAUSSIANS // 1000}k Gaussians, drawn at 512x384)",
                [breakdown("first image", first_timing[-1:]), breakdown("drag", drag, drag_s)])
    print_table("image route over HTTP, one request at a time (server timings from Server-Timing)", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
