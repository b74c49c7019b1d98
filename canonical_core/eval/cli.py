"""``canonical eval``: the evaluation protocol from the command line (argparse).

    canonical eval DATASET --views 2,4,8,16 --out DIR [--methods ...] [--noise 0.05,0.1,0.25,0.5]
                   [--mixed-noise 0.25]
    canonical eval LABELLED_DATASET --segmentation --views 2,4,8 --out DIR [--methods canonical:SETTING=VALUE,...]

`configure_parser` adds its arguments to a parser (the ``canonical`` console script's ``eval``),
`add_eval_parser` registers the subcommand on any subparsers object, and
``python -m canonical_core.eval DATASET ...`` runs it standalone.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import get_args

from ..datasets import MissingIntrinsics, load_dataset
from ..datasets.files import add_capture_options
from ..rendering import Colour
from .methods import METHODS
from .report import UnwritableFolder


def _list(kind: Callable[[str], object], name: str) -> Callable[[str], list]:
    def parse(text: str) -> list:
        if text.strip().lower() in ("", "none"):
            return []
        try:
            return [kind(part) for part in text.split(",") if part.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name}: expected a comma-separated list, got {text!r}") from None

    return parse


def configure_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    parser.add_argument("dataset", type=Path, help="capture folder (any layout load_dataset detects: tsdf-fusion/7-Scenes, TUM, transforms.json, deep-video-mvs, Redwood, label-fusion)")
    add_capture_options(parser)
    parser.add_argument("--views", type=_list(int, "views"), default=[2, 4, 8, 16], help="input view counts N (default 2,4,8,16); a capture needs at least "
                        "6 frames, and the inputs of every N with 10 frames left to hold out")
    parser.add_argument("--out", type=Path, required=True, help="output folder for results.json, results.md, PNGs")
    parser.add_argument("--methods", type=_list(str, "methods"), default=None,
                        help=f"comma-separated subset of {','.join(METHODS)} (default: all); a Scene method also as "
                             "NAME:SETTING=VALUE[:...], e.g. canonical:model=ckpt.safetensors")
    parser.add_argument("--noise", type=_list(float, "noise"), default=[],
                        help="depth-noise levels, sigma / median depth (e.g. 0.05,0.1,0.25,0.5; default none)")
    parser.add_argument("--mixed-noise", type=float, default=None, metavar="LEVEL",
                        help="also run with depth noise at LEVEL on every other input view only (uneven evidence; default off)")
    parser.add_argument("--scale", type=float, default=1.0, help="image downscale factor in (0, 1] (default 1)")
    parser.add_argument("--voxel-size", type=float, default=None, help="voxel edge in metres (default: 6 pixel footprints at the median depth)")
    parser.add_argument("--stability-views", type=_list(int, "stability-views"), default=None,
                        help="input counts of the feature-stability curve, the largest is the reference (default: those of "
                             "2..12 the capture has frames for; 'none' skips)")
    parser.add_argument("--no-extrapolation", action="store_true", help="skip the extrapolation split")
    parser.add_argument("--colour", choices=list(get_args(Colour)), default="normalised",
                        help="how Gaussians are rendered for scoring (rendering.render's colour modes; default normalised)")
    parser.add_argument("--segmentation", action="store_true",
                        help="run the segmentation experiment instead (label-fusion captures: fused label maps and a linear "
                             "probe at held-out views; default methods canonical,average,pixel_aligned)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no tables on stdout")
    return parser


def add_eval_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``eval`` on ``subparsers`` (from ``ArgumentParser.add_subparsers()``); the parsed
    namespace carries ``func=run_eval``."""
    parser = subparsers.add_parser("eval", help="evaluate methods on held-out views of a dataset",
                                   description=__doc__.split("\n\n")[0])
    configure_parser(parser)
    parser.set_defaults(func=run_eval)
    return parser


def _not_for_segmentation(args: argparse.Namespace) -> list[str]:
    """The options given that the segmentation experiment does not use (it would ignore them); those
    that only turn a part off (``--stability-views none``, ``--no-extrapolation``) ask for what it does
    anyway, so a command line shared by both experiments passes."""
    given = {"--noise": bool(args.noise), "--mixed-noise": args.mixed_noise is not None,
             "--stability-views": bool(args.stability_views), "--colour": args.colour != "normalised"}
    return [option for option, set_ in given.items() if set_]


def run_eval(args: argparse.Namespace) -> int:
    """Run `evaluate` (`evaluate_segmentation` with --segmentation) with the parsed arguments; prints
    results.md unless --quiet. Returns 0, or 2 (with the message on stderr) for invalid arguments,
    an --out that cannot be written among them (checked before the runs)."""
    from .run import evaluate
    from .segmentation import evaluate_segmentation

    if args.segmentation and (unused := _not_for_segmentation(args)):
        print(f"canonical eval: error: {', '.join(unused)}: not used by --segmentation (it scores fused labels, "
              "clean depth, held-out views between the inputs)", file=sys.stderr)
        return 2
    try:
        own = args.K is None and args.depth_scale is None
        dataset = args.dataset if own else load_dataset(args.dataset, K=args.K, depth_scale=args.depth_scale)
        if args.segmentation:
            evaluate_segmentation(dataset if own else [dataset], views=args.views, methods=args.methods or ("canonical", "average", "pixel_aligned"),
                                  out_dir=args.out, progress=not args.quiet, scale=args.scale, voxel_size=args.voxel_size)
        else:
            evaluate(dataset, views=args.views, methods=args.methods, noise=args.noise, mixed_noise=args.mixed_noise,
                     out_dir=args.out, progress=not args.quiet, scale=args.scale, voxel_size=args.voxel_size,
                     stability_views=args.stability_views, extrapolation=not args.no_extrapolation,
                     colour=args.colour)
    except UnwritableFolder as exc:
        print(f"canonical eval: error: --out: {exc.detail}", file=sys.stderr)
        return 2
    except (ValueError, ImportError) as exc:
        hint = " (here: --K fx,fy,cx,cy)" if isinstance(exc, MissingIntrinsics) else ""
        print(f"canonical eval: error: {exc}{hint}", file=sys.stderr)
        return 2
    if not args.quiet:
        print((Path(args.out) / "results.md").read_text())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = configure_parser(argparse.ArgumentParser(prog="python -m canonical_core.eval", description=__doc__.split("\n\n")[0]))
    args = parser.parse_args(argv)
    try:
        return run_eval(args)
    except KeyboardInterrupt:  # as the ``canonical`` command: one line, the shell's code for Ctrl-C
        print("interrupted", file=sys.stderr)
        return 130
