"""``demo``: start a service, stream a sample capture into it, write a render, a comparison and a PLY."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from canonical_core.datasets.files import add_capture_options  # imports no torch, no numba

from ..sdk import Client
from .capture import load_capture
from .common import UsageError, positive_number
from .launch import free_port, start_service
from .stream import FirstFrameSession, stream_frames, stream_summary


SHARED_SHELF = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "realsense_shelf"


def add_demo(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", nargs="?", default=None,
                   help="a capture to fuse (default: ../shared/data/realsense_shelf, else a generated sample)")
    p.add_argument("--out", default="out/demo", help="folder for the render, comparison, PLY and the service's data")
    p.add_argument("--voxel-size", type=positive_number, default=None,
                   help="default: 4 mm for the shelf, 2 cm for the sample; for a DATASET given, chosen by the service "
                        "from its first frame (as `canonical stream` does)")
    add_capture_options(p)
    p.add_argument("--port", type=int, default=0, help="port of the embedded service (default: a free one)")


def run_demo(args) -> int:
    from PIL import Image

    from canonical_core.datasets import synthetic_rgbd, write_tsdf_fusion

    out = Path(args.out)
    if not args.dataset and (args.K is not None or args.depth_scale is not None):
        raise UsageError(f"{'--K' if args.K is not None else '--depth-scale'}: only for a DATASET given (the sample's "
                         "files say their own)")
    if args.dataset:  # any capture, room-scale too: the service's rule fits the voxel to its depth
        path, voxel = Path(args.dataset), args.voxel_size
    elif SHARED_SHELF.is_dir():
        path, voxel = SHARED_SHELF, args.voxel_size or 0.004
    else:  # no data on this machine: generate a small RGB-D sequence (textured boxes, exact depth)
        path, voxel = out / "sample", args.voxel_size or 0.02
        if not path.is_dir():
            write_tsdf_fusion(synthetic_rgbd(num_frames=24, width=320, height=240), path)
    frames = load_capture(path, args)  # before --out is created: a mistyped capture leaves nothing behind
    out.mkdir(parents=True, exist_ok=True)
    port = args.port or free_port()
    size = "the voxel size the service chooses from the first frame" if voxel is None else f"{voxel * 1000:g} mm voxels"
    print(f"demo: fusing {len(frames)} frames of {path} at {size} through a service on port {port}")
    service = start_service(port, out / "data")
    try:
        with Client(f"http://127.0.0.1:{port}") as client:
            new_session = FirstFrameSession(client, {} if voxel is None else {"voxel_size": voxel})
            sent, elapsed = stream_frames(new_session, frames)
            session = new_session.session
            print(stream_summary(sent, elapsed, session, session.stats()))
            t0 = time.perf_counter()  # what the service shows once a stream pauses: its colours solved
            solved = session.wait_for_colours()
            if solved["colours_solved_frames"] == solved["frames"]:
                print(f"colours solved in the background {time.perf_counter() - t0:.1f} s after the last frame")
            view = frames[len(frames) // 2]
            cam = view.camera
            rendered = session.render(cam.K64(), cam.c2w64(), cam.width, cam.height)
            session.export_ply(out / "scene.ply")
    finally:
        service.terminate()
        service.wait(timeout=60)
    rgb = rendered["rgb"]  # uint8 [H, W, 3] on the wire
    truth = view.rgb.numpy()
    Image.fromarray(rgb).save(out / "render.png")
    Image.fromarray(np.concatenate([truth, rgb], 1)).save(out / "comparison.png")
    sq_err = ((rgb.astype(np.float64) - truth) / 255.0) ** 2
    covered = rendered["alpha"] > 0.5  # pixels the scene covers; nothing was seen at the others
    psnr = lambda mse: 10 * np.log10(1 / max(float(mse), 1e-12))  # noqa: E731
    print(f"rendered frame {view.frame_id} (an input view): PSNR {psnr(sq_err.mean()):.2f} dB over all pixels, "
          f"covered PSNR {psnr(sq_err[covered].mean()):.2f} dB on the {100 * covered.mean():.0f} % of pixels the scene covers")
    print(f"wrote {out / 'render.png'}, {out / 'comparison.png'} (truth | render) and {out / 'scene.ply'}")
    return 0
