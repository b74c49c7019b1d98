"""Labelled frames: a class map sent as its ids against the same labels sent as one-hot scores.

    python bench/labels.py [--classes 3,16,40,64] [--frames 12]

For each K, the shelf's first frames (640x480, with depth) carry a class map of K classes (blocks
of the image, every class present) and go through each step a labelled frame takes, both ways:

- client: `frame_body` with the SDK's compact codec (the scores: the map one-hot encoded as float16,
  what the SDK sent before class maps travelled as ids; the map: int16 ids with ``num_classes``),
  its time and the body's bytes;
- service: the body decoded and checked into a `Frame` (`server.wire.frame_from_message`);
- fold: `Scene.fold` of that frame into a scene at 4 mm that folds the same frames the same way.

Per K and form: the median over the frames (after a warm-up frame); the scores over the map as a
ratio. Both forms fold the same scene: their digests are compared and printed. Never asserts timings.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))
from common import machine_summary, print_table  # noqa: E402

DATA = HERE.parents[1] / "shared" / "data"


def class_map(height: int, width: int, classes: int) -> np.ndarray:  # [H, W] int64, every class present
    """Blocks of 40 x 53 pixels numbered across the image, modulo K: every class present, edges everywhere."""
    return (np.arange(height)[:, None] // 40 * 7 + np.arange(width)[None, :] // 53) % classes


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--classes", default="3,16,40,64", help="K values, comma-separated (the service allows 64 by default)")
    p.add_argument("--frames", type=int, default=12, help="shelf frames a K (the first one warms up)")
    args = p.parse_args()

    from canonical_core import Scene, SceneConfig
    from canonical_core.datasets import load_dataset
    from client.sdk import frame_body, unpack
    from server.wire import FrameLimits, frame_from_message

    frames = list(load_dataset(DATA / "realsense_shelf", max_frames=args.frames))
    print(machine_summary())
    rows, digests = [], []
    for classes in (int(k) for k in args.classes.split(",")):
        ids = class_map(frames[0].height, frames[0].width, classes)

        def labelled(form: str) -> dict:  # `frame_body`'s label arguments; the one-hot encoding is the client's work
            if form == "scores":
                return {"labels": (ids[..., None] == np.arange(classes)).astype(np.float16)}
            return {"labels": ids, "num_classes": classes}

        per_form = {}
        for form in ("scores", "class map"):
            scene = Scene(SceneConfig(voxel_size=0.004))
            client_ms, service_ms, fold_ms, sizes = [], [], [], []
            for frame in frames:
                t0 = time.perf_counter()
                body = frame_body(frame.rgb.numpy(), frame.camera.K64(), frame.camera.c2w64(), depth=frame.depth.numpy(),
                                  **labelled(form))
                t1 = time.perf_counter()
                decoded = frame_from_message(unpack(body), limits=FrameLimits(max_label_channels=256))
                t2 = time.perf_counter()
                scene.fold(decoded)
                t3 = time.perf_counter()
                client_ms.append((t1 - t0) * 1000)
                service_ms.append((t2 - t1) * 1000)
                fold_ms.append((t3 - t2) * 1000)
                sizes.append(len(body))
            per_form[form] = [float(np.median(v[1:])) for v in (client_ms, service_ms, fold_ms, sizes)]
            digests.append(scene.digest())
        for form, (client, service, fold, size) in per_form.items():
            rows.append({"K": classes, "labels sent as": form, "client ms": f"{client:.1f}", "body MB": f"{size / 1e6:.3f}",
                         "service decode ms": f"{service:.1f}", "fold ms": f"{fold:.1f}",
                         "all three ms": f"{client + service + fold:.1f}"})
        (c0, s0, f0, b0), (c1, s1, f1, b1) = per_form["scores"], per_form["class map"]
        rows.append({"K": classes, "labels sent as": "scores / map", "client ms": f"{c0 / c1:.2f}x",
                     "body MB": f"{b0 / b1:.2f}x", "service decode ms": f"{s0 / s1:.2f}x", "fold ms": f"{f0 / f1:.2f}x",
                     "all three ms": f"{(c0 + s0 + f0) / (c1 + s1 + f1):.2f}x"})
        print(f"K = {classes}: the two forms fold the same scene: {digests[-2] == digests[-1]}", flush=True)
    print_table(f"a labelled 640x480 frame, median over {args.frames - 1} shelf frames (ms, MB)", rows)


if __name__ == "__main__":
    main()
