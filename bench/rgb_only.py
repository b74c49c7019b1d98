"""Fusion from RGB only (plane-sweep depth) vs RGB-D on the same frames, and reliability vs uniform.

    python bench/rgb_only.py [--data ../shared/data/realsense_shelf] [--views 4,8,16] [--scale 0.5] [--voxel 0.008]
                             [--window-views 8] [--window-step 6] [--solve-views K]

The evaluation's protocol and scoring (`canonical_core.eval`): inputs and held-out frames from
`interpolation_split` for each N in ``views`` (one table per N), frames resized by `resize_frame`
(colour area-averaged, depth nearest), all-pixel and covered PSNR from `score`. RGB-only inputs are
the same frames with their depth removed; held-out frames keep theirs (the score's depth agreement
uses it).

A second table per N asks whether reliability does its job, telling surface from floaters, on the RGB-only
scenes: the AUC with which a voxel-level quantity (the method's R_scene, which sets its opacity, or
the observation count) separates voxels on the sensor's surface from the rest. A voxel is on the
surface when it is within one voxel (26-neighbourhood) of a voxel that a sensor depth point of any
frame of the capture falls in.

A last table asks whether the reliability-vs-uniform figure is a property of the method or of one
split: RGB-only fusion, full against no_reliability, over every window of ``window_views`` inputs
``window_step`` frames apart (offsets 0, 1, ...), each scored on the frames midway between its
consecutive inputs (never inputs). It reports each window, the mean and median differences and
how many windows reliability wins (``--window-views 0`` skips it).

``--solve-views K`` runs every scene with `SceneConfig.colour_solve.views` K (colours solved against
up to K kept inputs), so the comparisons can be made with the colour solve too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import canonical_core as cc  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.methods import SplatModel  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import score  # noqa: E402
from canonical_core.eval.mvs_eval import without_depth  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402
from canonical_core.scene.batch import voxel_keys  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def surface_keys(frames, voxel: float) -> torch.Tensor:  # -> [K] int64, sorted
    """Keys of the voxels within one voxel of a sensor depth point of ``frames``."""
    offsets = torch.stack(torch.meshgrid(*[torch.tensor([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = []
    for f in frames:
        v, u = torch.nonzero(f.depth > 0, as_tuple=True)
        points = f.camera.lift(torch.stack([u, v], -1).float(), f.depth[v, u])
        centres = (torch.floor(points / voxel) + 0.5) * voxel
        keys += [torch.unique(voxel_keys(centres + o * voxel, voxel)) for o in offsets]
    return torch.unique(torch.cat(keys))


def auc(score: torch.Tensor, positive: torch.Tensor) -> float:
    """Area under the ROC curve of ``score`` for ``positive`` (ties count one half).

    Example:
        >>> auc(torch.tensor([0.1, 0.4, 0.4, 0.9]), torch.tensor([False, False, True, True]))
        0.875
    """
    _, inverse, counts = torch.unique(score.double(), return_inverse=True, return_counts=True)
    ranks = (torch.cumsum(counts, 0) - (counts - 1) / 2.0)[inverse]  # average rank of tied values
    n_pos = int(positive.sum())
    n_neg = positive.numel() - n_pos
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def views_list(text: str) -> list[int]:
    """``"4,8,16"`` -> [4, 8, 16] (argparse type)."""
    try:
        views = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated view counts, got {text!r}") from None
    if not views or min(views) < 2:
        raise argparse.ArgumentTypeError(f"expected view counts >= 2, got {text!r}")
    return views


def fused_metrics(inputs, weighting: str, voxel: float, targets, solve_views: int = 0) -> tuple[dict, cc.Scene]:
    """The evaluation's metrics of ``targets`` rendered from a scene folded from ``inputs``, and the scene."""
    scene = cc.Scene(cc.SceneConfig(voxel_size=voxel, research={"weighting": weighting}, colour_solve={"views": solve_views}))
    for frame in inputs:
        scene.fold(frame)
    return score(SplatModel(scene.decode()), targets, voxel).metrics, scene


def shifted_windows(small, views: int, step: int, voxel: float, solve_views: int = 0) -> None:
    """RGB-only full against no_reliability over every window of ``views`` inputs ``step`` apart."""
    rows, diffs = [], []
    for offset in range(len(small) - step * (views - 1)):
        inputs = [offset + step * k for k in range(views)]
        targets = [small[i + step // 2] for i in inputs[:-1]]
        rgb_only = [without_depth(small[i]) for i in inputs]
        pair = [fused_metrics(rgb_only, w, voxel, targets, solve_views)[0] for w in ("full", "no_reliability")]
        psnr = np.array([[m["psnr"], m["psnr_covered"]] for m in pair])
        diffs.append(psnr[0] - psnr[1])
        rows.append({"inputs": f"{inputs[0]}..{inputs[-1]}", "full PSNR / covered dB": f"{psnr[0, 0]:.2f} / {psnr[0, 1]:.2f}",
                     "no_reliability": f"{psnr[1, 0]:.2f} / {psnr[1, 1]:.2f}",
                     "full - no_reliability": f"{diffs[-1][0]:+.2f} / {diffs[-1][1]:+.2f}"})
    if not rows:
        print(f"(no window of {views} inputs {step} frames apart fits in {len(small)} frames)\n")
        return
    d = np.array(diffs)
    for label, v in (("mean", d.mean(0)), ("median", np.median(d, 0))):
        rows.append({"inputs": label, "full - no_reliability": f"{v[0]:+.2f} / {v[1]:+.2f}"})
    wins = (d > 0).sum(0)
    rows.append({"inputs": "windows full wins", "full - no_reliability": f"{wins[0]} / {wins[1]} of {len(d)}"})
    solved = f", colours solved against {solve_views} kept inputs" if solve_views else ""
    print_table(f"RGB only, {views} inputs {step} frames apart, every offset: reliability against uniform "
                f"(held out: the frames midway between inputs){solved}", rows)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--views", type=views_list, default=[4, 8, 16], help="input view counts, e.g. 4,8,16")
    p.add_argument("--scale", type=float, default=0.5, help="image scale (0.5: 640x480 -> 320x240)")
    p.add_argument("--voxel", type=float, default=0.008)
    p.add_argument("--window-views", type=int, default=8, help="inputs per shifted window (0: skip that table)")
    p.add_argument("--window-step", type=int, default=6, help="frames between a shifted window's inputs")
    p.add_argument("--solve-views", type=int, default=0, help="colour_solve.views of every scene (0: no colour solve)")
    args = p.parse_args(argv)
    view_counts = args.views
    if not 0 <= args.solve_views <= 64:
        p.error(f"--solve-views: expected 0 to 64 kept views, got {args.solve_views}")
    if args.window_views and (args.window_views < 2 or args.window_step < 2):
        p.error("--window-views needs at least 2 inputs and --window-step at least 2 frames (a held-out frame between inputs)")
    frames = load_dataset(args.data)
    split = interpolation_split(len(frames), view_counts)
    small = [resize_frame(f, args.scale) for f in frames]
    surface = surface_keys(small, args.voxel)
    print(machine_summary())
    targets = [small[i] for i in split.heldout]
    for views in view_counts:
        rgbd = [small[i] for i in split.inputs[views]]
        rgb_only = [without_depth(f) for f in rgbd]
        rows, auc_rows = [], []
        for label, inputs, weighting in (("RGB-D", rgbd, "full"), ("RGB only", rgb_only, "full"),
                                         ("RGB-D, no_reliability", rgbd, "no_reliability"),
                                         ("RGB only, no_reliability", rgb_only, "no_reliability")):
            metrics, scene = fused_metrics(inputs, weighting, args.voxel, targets, args.solve_views)
            rows.append({"input": label, "PSNR dB": f"{metrics['psnr']:.2f}",
                         "covered PSNR dB": f"{metrics['psnr_covered']:.2f}", "SSIM": f"{metrics['ssim']:.3f}",
                         "depth agreement": f"{metrics['depth_agreement']:.3f}",
                         "Gaussians": f"{metrics['gaussians']:,}"})
            if inputs is rgb_only:
                f = scene.fields()
                on_surface = torch.isin(f["keys"], surface)
                auc_rows.append({"RGB-only scene": weighting, "voxels": f"{on_surface.numel():,}",
                                 "on surface": f"{float(on_surface.double().mean()):.3f}",
                                 "AUC of R_scene": f"{auc(f['reliability'], on_surface):.3f}",
                                 "AUC of observation count": f"{auc(f['observations'], on_surface):.3f}"})
        size = f"{targets[0].width}x{targets[0].height}"
        print_table(f"{views} input views {list(split.inputs[views])}, {len(targets)} held-out frames "
                    f"{list(split.heldout)}, {size}, {args.voxel * 1000:g} mm voxels", rows)
        print_table(f"{views} input views: does R_scene tell surface voxels from floaters? "
                    "(sensor depth of all frames as truth)", auc_rows)
    if args.window_views:
        shifted_windows(small, args.window_views, args.window_step, args.voxel, args.solve_views)


if __name__ == "__main__":
    main()
