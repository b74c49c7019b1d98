"""The commands that run the library here on captures, without a service: ``depth`` (plane-sweep depth
and uncertainty pictures), ``train`` (the decoder's heads) and ``eval`` (methods on held-out views)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from canonical_core.datasets.files import add_capture_options  # imports no torch, no numba

from .capture import load_capture
from .common import UsageError, positive_int


# -- depth --------------------------------------------------------------------------------------
def add_depth(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="a capture canonical_core.datasets.load_dataset reads (its depth, if any, is only compared against)")
    p.add_argument("--out", required=True, help="folder for <frame>.depth.png and <frame>.uncertainty.png")
    p.add_argument("--sources", type=positive_int, default=2, help="source views per frame (default 2)")
    p.add_argument("--stride", type=positive_int, default=1)
    p.add_argument("--max-frames", type=positive_int, default=None)
    add_capture_options(p)


def run_depth(args) -> int:
    import sys

    from tqdm import tqdm

    from canonical_core.eval.mvs_preview import write_depth_previews
    from canonical_core.eval.report import UnwritableFolder, check_writable

    frames = load_capture(args.dataset, args, stride=args.stride, max_frames=args.max_frames)
    try:  # before the frames are swept, which take a second or more each
        check_writable(args.out, "--out")
    except UnwritableFolder as exc:
        raise UsageError(str(exc)) from None
    with tqdm(total=len(frames), file=sys.stderr, desc="depth", unit="frame", dynamic_ncols=True) as bar:
        rows = write_depth_previews(frames, args.out, num_sources=args.sources, progress=bar.update)
    errors = [r["median_abs_rel"] for r in rows if r.get("median_abs_rel") is not None]
    summary = f"; median AbsRel vs the sensor {np.median(errors):.4f}" if errors else ""
    print(f"wrote depth and uncertainty pictures of {len(rows)} frames to {args.out}{summary}")
    return 0


# -- train --------------------------------------------------------------------------------------
def add_train(p: argparse.ArgumentParser) -> None:
    p.add_argument("captures", nargs="+", help="RGB-D capture folders (never the evaluation capture, realsense_shelf)")
    p.add_argument("--out", required=True, help="the checkpoint to write (.safetensors); the report goes to <stem>_report/")
    p.add_argument("--seed", type=int, default=0, help="seed of the samples, the step order and the initial heads (default 0)")
    p.add_argument("--steps", type=int, default=400, help="optimisation steps (default 400)")
    p.add_argument("--minutes", type=float, default=None, help="stop after this many minutes even if steps remain")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="where the decode and render run (default cpu)")
    p.add_argument("--width", type=int, default=160, help="training image width in pixels (default 160)")
    p.add_argument("--coverage-weight", type=float, default=0.0,
                   help="weight of the coverage term (1 - alpha)^2 at pixels with measured depth (default 0)")
    p.add_argument("--heads", default=None,
                   help="comma-separated heads to train (default all: opacity,free_space_penalty,offset,log_scale_delta,color_delta)")
    add_capture_options(p)


# run_training's ValueErrors that are about an argument, whatever the captures' files hold: their field -> its flag
_TRAIN_FLAGS = (("out: ", "--out"), ("K: ", "--K"), ("depth_scale: ", "--depth-scale"))


def run_train(args) -> int:
    """Train with the parsed arguments. A usage error (exit 2) names its flag or argument: a setting, a
    capture path with nothing there or the evaluation capture's, an --out that cannot be written, a
    capture without intrinsics and no --K; a capture's own files' problems exit 1, as the stream's."""
    from canonical_core.datasets import MissingIntrinsics
    from canonical_core.train.data import RefusedCapture
    from canonical_core.train.loop import TrainSettings, run_training

    heads = {} if args.heads is None else {"heads": tuple(h.strip() for h in args.heads.split(",") if h.strip())}
    try:
        settings = TrainSettings(seed=args.seed, steps=args.steps, minutes=args.minutes, width=args.width,
                                 device=args.device, coverage_weight=args.coverage_weight, **heads)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        result = run_training(args.captures, args.out, settings, K=args.K, depth_scale=args.depth_scale)
    except MissingIntrinsics as exc:
        raise UsageError(f"--K: {exc} (here: --K fx,fy,cx,cy)") from None
    except RefusedCapture as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:
        for field, flag in _TRAIN_FLAGS:  # a capture's own K or depth units: its files' problem, exit 1
            if str(exc).startswith(field) and (flag != "--K" or args.K is not None) \
                    and (flag != "--depth-scale" or args.depth_scale is not None):
                raise UsageError(f"{flag}: {str(exc).removeprefix(field)}") from None
        raise
    report = Path(args.out).with_name(Path(args.out).stem + "_report")
    print(f"{result.steps} steps in {result.seconds / 60:.1f} min; wrote {args.out} and {report}/")
    print((report / "report.md").read_text())
    return 0


# -- eval ---------------------------------------------------------------------------------------
# canonical_core (torch) is imported only when `eval` is the command: the other commands start fast.
def add_eval(p: argparse.ArgumentParser) -> None:
    from canonical_core.eval.cli import configure_parser

    configure_parser(p)


def run_eval(args) -> int:
    from canonical_core.eval import cli

    return cli.run_eval(args)
