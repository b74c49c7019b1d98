"""The segmentation experiment: fused labels rendered at held-out views, and a linear probe on
splatted features.

Per labelled capture (a label-fusion bin: per-frame label maps, read as one-hot `Frame.labels`
with one channel per label id found in the capture), method and number of input views N:

- **Label fusion.** The method is built from the N input frames with their label scores (the scene
  fuses them per voxel; pixel-aligned Gaussians carry their pixel's scores), the label scores are
  splatted at every held-out camera and the argmax is the predicted label map.
- **Linear probe.** The method's feature splat (the composited features divided by the accumulated
  opacity) is rendered at the input cameras; a multinomial logistic regression (`fit_probe`) is
  trained on the covered pixels there against the input frames' labels, then predicts the label
  of every covered pixel of the feature splats at the held-out cameras. Features: the scene's own
  (``SceneConfig.features.backend`` default), and, when every frame of the capture carries client
  features (`Frame.features`), the same probe on a scene that fuses those
  (``features.backend="client"``; Scene methods only, pixel-aligned Gaussians use the default).

Split: a bin holds few frames (15 in ``apc_bins``), too few for the main protocol's ten held-out
frames besides eight inputs, so every ``heldout_every``-th frame is held out starting at position 1
(1, 4, 7, ...; 5 of 15 with the default 3) and the N inputs are spread evenly over the remaining
frames (`segmentation_split`).

Metrics, from one confusion matrix per (capture, method, N) summed over the held-out frames:

- a pixel is covered where the render's accumulated opacity is at least
  `metrics.COVERAGE_THRESHOLD`, and only covered pixels get a predicted label;
- ``covered``: pixel accuracy and mIoU over the covered pixels only;
- ``all`` pixels: every pixel counts, an uncovered one as wrong (a miss of its true class that is
  no false positive of any class), so a method cannot gain by drawing less;
- mIoU is the mean IoU = TP / (TP + FP + FN) over the classes present in the ground truth or in
  the prediction of the pixels scored; a class in neither is left out (not counted as 0 or 1).

Example:
    >>> gt = torch.tensor([[0, 0], [1, 1]])
    >>> pred = torch.tensor([[0, 1], [1, -1]])  # -1: uncovered
    >>> round(scores(label_confusion(gt, pred, 3))["miou"], 4)  # IoU 1/2 (class 0) and 1/3 (class 1); class 2 absent
    0.4167
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ..datasets import FrameSequence, load_label_fusion
from ..datasets.label_fusion import has_label_maps
from ..datasets.tsdf_fusion import find_frames_folder
from ..evidence.features import sample_client_features
from ..frame import Frame, resize_frame
from ..rendering import render
from .methods import MethodSpec, SceneBuilder, SplatModel, parse_method
from .metrics import covered
from .probe import PROBE_STEPS, PROBE_WEIGHT_DECAY, fit_probe
from .protocol import Split, spread
from .figures import require_matplotlib
from .report import _num, check_writable
from .segmentation_report import write_partial_segmentation_report, write_segmentation_report

HELDOUT_EVERY = 3
PROBE_PIXELS = 20000  # most training pixels per probe, drawn with a fixed seed
PROBE_SEED = 0
GRID_ROWS = 3  # held-out frames shown per grid (first, middle, last)
# label colours of the grids by channel; uncovered pixels are black
PALETTE = np.array([(128, 128, 128), (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
                    (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60)], np.uint8)
METRICS = ("miou", "accuracy", "miou_covered", "accuracy_covered")


# -- metrics ---------------------------------------------------------------------------------------
def label_confusion(
    gt: Tensor,  # [H, W] int64 class index in [0, S)
    pred: Tensor,  # [H, W] int64 class index in [0, S), or -1 where nothing is predicted
    classes: int,
    mask: Tensor | None = None,  # [H, W] bool, pixels to score (default all)
) -> Tensor:  # [S, S + 1] int64: rows true class, columns predicted class, last column "no prediction"
    """Confusion counts of ``pred`` against ``gt`` over the pixels of ``mask``."""
    if isinstance(classes, bool) or not isinstance(classes, int) or classes < 1:
        raise ValueError(f"classes: expected a positive integer, got {classes!r}")
    if gt.shape != pred.shape:
        raise ValueError(f"pred: shape {list(pred.shape)} does not match gt {list(gt.shape)}")
    if mask is not None and mask.shape != gt.shape:
        raise ValueError(f"mask: shape {list(mask.shape)} does not match gt {list(gt.shape)}")
    if gt.numel() and (int(gt.min()) < 0 or int(gt.max()) >= classes):
        raise ValueError(f"gt: class indices must lie in [0, {classes}), got {int(gt.min())}..{int(gt.max())}")
    if pred.numel() and (int(pred.min()) < -1 or int(pred.max()) >= classes):
        raise ValueError(f"pred: class indices must lie in [-1, {classes}), got {int(pred.min())}..{int(pred.max())}")
    g, p = gt.reshape(-1).long(), pred.reshape(-1).long()
    if mask is not None:
        g, p = g[mask.reshape(-1)], p[mask.reshape(-1)]
    p = torch.where(p < 0, classes, p)
    return torch.bincount(g * (classes + 1) + p, minlength=classes * (classes + 1)).reshape(classes, classes + 1)


def scores(confusion: Tensor) -> dict:
    """Pixel accuracy, mIoU and per-class IoU (None for a class in neither ground truth nor
    prediction) of a `label_confusion` matrix; accuracy and mIoU are None when no pixel was scored."""
    S = confusion.shape[0]
    if confusion.ndim != 2 or confusion.shape[1] != S + 1:
        raise ValueError(f"confusion: expected shape [S, S + 1], got {list(confusion.shape)}")
    c = confusion.double()
    tp = c[:, :S].diagonal()
    union = c.sum(1) + c[:, :S].sum(0) - tp
    iou = [float(tp[k] / union[k]) if union[k] > 0 else None for k in range(S)]
    present = [v for v in iou if v is not None]
    total = float(c.sum())
    return {"miou": float(np.mean(present)) if present else None,
            "accuracy": float(tp.sum()) / total if total else None, "iou": iou}


def label_map(frame: Frame, size: tuple[int, int] | None = None) -> Tensor:  # [H, W] int64
    """The class of every pixel of a (height, width) image (default the frame's): a class map's id
    (-1: none), or the argmax of label scores, looked up nearest as fusion samples client maps."""
    if frame.labels is None:
        raise ValueError(f"labels: frame {frame.frame_id!r} carries no labels")
    H, W = size or (frame.height, frame.width)
    rows, cols = (a.reshape(-1) for a in np.mgrid[0:H, 0:W])
    ids = (frame.labels if frame.labels.ndim == 2 else frame.labels.argmax(-1)).numpy()[..., None]
    return torch.from_numpy(sample_client_features(ids, rows, cols, (H, W)).reshape(H, W)).long()


# -- renders ---------------------------------------------------------------------------------------
def render_labels(model: SplatModel, frame: Frame) -> Tensor:  # [H, W] int64, -1 where uncovered
    """The argmax of the splatted label scores at the frame's camera, on covered pixels."""
    out = render(model.splats, frame.camera, outputs=("labels", "alpha"))
    return torch.where(covered(out.alpha), out.labels, -1)


def render_features(model: SplatModel, frame: Frame) -> tuple[Tensor, Tensor]:  # [H, W, C], [H, W] bool
    """The feature splat at the frame's camera, normalised by the accumulated opacity, and the
    covered pixels."""
    out = render(model.splats, frame.camera, outputs=("features", "alpha"))
    return out.features / out.alpha.clamp_min(1e-6)[..., None], covered(out.alpha)


def probe_confusion(model: SplatModel, inputs: Sequence[Frame], targets: Sequence[Frame], classes: int) -> tuple[Tensor, Tensor]:
    """Train a probe on ``model``'s feature splats at the inputs, score it at the targets:
    the confusion over all target pixels and over the covered ones."""
    xs, ys = [], []
    for frame in inputs:
        feats, mask = render_features(model, frame)
        xs.append(feats[mask])
        ys.append(label_map(frame)[mask])
    x, y = torch.cat(xs), torch.cat(ys)
    if len(x) == 0:
        raise ValueError("features: the method covers no pixel of its input views; nothing to train the probe on")
    if len(x) > PROBE_PIXELS:
        keep = torch.randperm(len(x), generator=torch.Generator().manual_seed(PROBE_SEED))[:PROBE_PIXELS]
        x, y = x[keep], y[keep]
    probe = fit_probe(x, y, classes)
    all_pixels = torch.zeros(classes, classes + 1, dtype=torch.int64)
    on_covered = torch.zeros_like(all_pixels)
    for frame in targets:
        feats, mask = render_features(model, frame)
        pred = torch.full(mask.shape, -1, dtype=torch.int64)
        pred[mask] = probe.predict(feats[mask])
        gt = label_map(frame)
        all_pixels += label_confusion(gt, pred, classes)
        on_covered += label_confusion(gt, pred, classes, mask)
    return all_pixels, on_covered


# -- the experiment --------------------------------------------------------------------------------
def segmentation_split(n: int, views: Sequence[int], every: int = HELDOUT_EVERY) -> Split:
    """Held out: positions 1, 1 + every, ...; inputs for N: N positions spread evenly over the rest.

    Example:
        >>> split = segmentation_split(15, [2, 4, 8])
        >>> split.heldout, split.inputs[4]
        ((1, 4, 7, 10, 13), (0, 5, 9, 14))
    """
    if isinstance(every, bool) or not isinstance(every, int) or every < 2:
        raise ValueError(f"heldout_every: expected an integer of at least 2, got {every!r}")
    if not views or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in views):
        raise ValueError(f"views: expected a non-empty list of positive integers, got {list(views)!r}")
    heldout = tuple(range(1, n, every))
    free = [p for p in range(n) if p not in heldout]
    if not heldout or max(views) > len(free):
        raise ValueError(f"views: {max(views)} input views requested, but {n} frames with one in every {every} held out "
                         f"leave {len(free)} inputs and {len(heldout)} held out")
    return Split(heldout=heldout, inputs={v: tuple(free[i] for i in spread(len(free), v)) for v in sorted(set(views))})


def parse_label_method(text: str) -> MethodSpec:
    """`methods.parse_method` for this experiment: also refuses a method that cannot splat labels
    and features here.

    Example:
        >>> parse_label_method("canonical:sh_degree=0").settings
        {'sh_degree': 0}
    """
    spec = parse_method(text)
    method = spec.method()
    if not method.features or method.unavailable() is not None:
        raise ValueError(f"methods: {spec.name} cannot splat labels and features here")
    return spec


def find_bins(path: str | Path) -> list[Path]:
    """The label-fusion captures at ``path``: the folder itself when it is one, else its subfolders
    that are (sorted by name)."""
    root = Path(path)
    if not root.is_dir():
        raise ValueError(f"dataset: {root}: not a folder")

    def labelled(folder: Path) -> bool:
        try:
            frames = find_frames_folder(folder)
        except ValueError:  # frames in several subfolders: each may be a capture
            return False
        return frames is not None and has_label_maps(frames)

    if labelled(root):
        return [root]
    bins = [d for d in sorted(root.iterdir()) if d.is_dir() and labelled(d)]
    if not bins:
        raise ValueError(f"dataset: {root}: no label-fusion capture (frame-NNNNNN.segm.png or .mask.png label maps) "
                         f"in it or its subfolders")
    return bins


def _load(sequence: FrameSequence, positions: Sequence[int], scale: float) -> dict[int, Frame]:
    """Frames at ``scale``; labels and client features stay at their own resolution (looked up nearest)."""
    frames = {}
    for p in positions:
        frame = sequence[p]
        if frame.labels is None:
            raise ValueError(f"labels: frame {frame.frame_id!r} of {sequence.name} carries no labels")
        frames[p] = replace(resize_frame(frame, scale), labels=frame.labels, num_classes=frame.num_classes,
                            features=frame.features)
    return frames


def colour_labels(ids: Tensor) -> np.ndarray:  # [H, W] int64 (-1 = none) -> [H, W, 3] uint8
    """`PALETTE` colours by label channel (cycling), black where nothing is predicted."""
    out = PALETTE[ids.clamp_min(0).numpy() % len(PALETTE)]
    out[ids.numpy() < 0] = 0
    return out


def _row(kind: str, all_pixels: Tensor, on_covered: Tensor, label_ids: Sequence[int]) -> dict:
    a, c = scores(all_pixels), scores(on_covered)
    return {f"{kind}_miou": a["miou"], f"{kind}_accuracy": a["accuracy"], f"{kind}_miou_covered": c["miou"],
            f"{kind}_accuracy_covered": c["accuracy"], f"{kind}_iou": dict(zip(map(str, label_ids), a["iou"]))}


def run_bin(sequence: FrameSequence, views: Sequence[int], specs: Sequence[MethodSpec], scale: float,
            voxel_size: float | None, heldout_every: int, probe: bool, bar: tqdm, bins: list[dict]) -> dict:
    """Every method and N on one capture: its results are appended to ``bins`` as soon as its frames
    are read, each run's row as it finishes (an interrupted experiment reports what finished); returns
    its grids {N: {column: images}}."""
    from .run import default_voxel_size

    label_ids = list(getattr(sequence, "label_ids", ()))
    split = segmentation_split(len(sequence), views, heldout_every)
    frames = _load(sequence, sorted(set(split.heldout).union(*split.inputs.values())), scale)
    S = {f.label_dim for f in frames.values()}
    if len(S) != 1:
        raise ValueError(f"labels: frames of {sequence.name} carry different channel counts {sorted(S)}")
    S = S.pop()
    label_ids = label_ids if len(label_ids) == S else list(range(S))
    client = all(f.features is not None for f in frames.values())
    targets = [frames[p] for p in split.heldout]
    if voxel_size is None:
        voxel_size = default_voxel_size([frames[p] for p in split.inputs[max(split.inputs)]])
    grid_at = sorted({0, len(targets) // 2, len(targets) - 1})[:GRID_ROWS]
    grids = {n: {"image": [targets[i].rgb.numpy() for i in grid_at],
                 "ground truth": [colour_labels(label_map(targets[i])) for i in grid_at]} for n in split.inputs}
    runs = []
    bins.append({"dataset": sequence.name, "frames": len(sequence), "frame_ids": sequence.frame_ids,
                 "label_ids": label_ids, "image_size": [targets[0].width, targets[0].height], "voxel_size": voxel_size,
                 "heldout": list(split.heldout), "inputs": {str(k): list(v) for k, v in split.inputs.items()},
                 "client_features": client, "runs": runs})
    for n, positions in split.inputs.items():
        inputs = [frames[p] for p in positions]
        for spec in specs:
            model = spec.method().build(inputs, voxel_size, True)
            all_pixels = torch.zeros(S, S + 1, dtype=torch.int64)
            on_covered = torch.zeros_like(all_pixels)
            preds = []
            for frame in targets:
                pred, gt = render_labels(model, frame), label_map(frame)
                all_pixels += label_confusion(gt, pred, S)
                on_covered += label_confusion(gt, pred, S, pred >= 0)
                preds.append(pred)
            grids[n][spec.label] = [colour_labels(preds[i]) for i in grid_at]
            row = {"dataset": sequence.name, "method": spec.label, "views": n, "gaussians": model.gaussians,
                   "coverage": float(on_covered.sum()) / float(all_pixels.sum()), **_row("fusion", all_pixels, on_covered, label_ids)}
            if probe:
                row |= _row("probe", *probe_confusion(model, inputs, targets, S), label_ids)
                if client and isinstance(spec.method().build, SceneBuilder):
                    C = int(inputs[0].features.shape[-1])
                    client_model = spec.method({"features.backend": "client", "features.dim": C}).build(inputs, voxel_size, True)
                    row |= _row("client_probe", *probe_confusion(client_model, inputs, targets, S), label_ids)
            runs.append(row)
            bar.set_postfix_str(f"{sequence.name} {spec.label} N={n}: mIoU {_num(row['fusion_miou'], 3)}")
            bar.update()
    return grids


def mean_runs(bins: Sequence[Mapping]) -> list[dict]:
    """Per (method, N) the mean of every metric over the captures that have it (None when none has)."""
    keys = ("coverage", *(f"{k}_{m}" for k in ("fusion", "probe", "client_probe") for m in METRICS))
    groups: dict[tuple, list[dict]] = {}
    for b in bins:
        for r in b["runs"]:
            groups.setdefault((r["method"], r["views"]), []).append(r)
    out = []
    for (method, n), rows in groups.items():
        row = {"dataset": "mean", "method": method, "views": n}
        for k in keys:
            values = [r[k] for r in rows if r.get(k) is not None]
            row[k] = float(np.mean(values)) if values and len(values) == len(rows) else None
        out.append(row)
    return out


def evaluate_segmentation(
    dataset: str | Path | Sequence[FrameSequence],
    views: Sequence[int] = (2, 4, 8),
    methods: Sequence[str] = ("canonical", "average", "pixel_aligned"),
    out_dir: str | Path = "eval_segmentation",
    progress: bool = True,
    scale: float = 1.0,
    voxel_size: float | None = None,
    heldout_every: int = HELDOUT_EVERY,
    probe: bool = True,
) -> dict:
    """Run the experiment (module docstring) on every labelled capture of ``dataset`` and write
    results.json, results.md, miou_vs_views.png and the label grids into ``out_dir``; returns the
    results dict (the JSON content).

    Args:
        dataset: a label-fusion capture folder, a folder of them (e.g. ``apc_bins``: each bin is
            evaluated, and the mean over bins reported), or labelled FrameSequences.
        views: input counts N.
        methods: `parse_label_method` specs, e.g. ``canonical`` or ``canonical:model=PATH``.
        scale: image downscale factor in (0, 1] (label maps stay full size and are looked up nearest).
        voxel_size: voxel edge in metres; default `run.default_voxel_size` of each capture's largest-N inputs.
        heldout_every: hold out every this-many-th frame (from position 1).
        probe: also run the linear probe.
    """
    require_matplotlib()
    if isinstance(methods, str) or not methods:
        raise ValueError(f"methods: expected a non-empty list of method specs, got {methods!r}")
    specs = list({s.label: s for s in map(parse_label_method, methods)}.values())
    if not (isinstance(scale, (int, float)) and 0 < scale <= 1):
        raise ValueError(f"scale: expected a number in (0, 1], got {scale!r}")
    if voxel_size is not None and not voxel_size > 0:
        raise ValueError(f"voxel_size: expected a positive number, got {voxel_size!r}")
    if isinstance(dataset, (str, Path)):
        sequences = [load_label_fusion(b) for b in find_bins(dataset)]
    else:
        sequences = list(dataset)
    for seq in sequences:
        segmentation_split(len(seq), views, heldout_every)  # checks before the long run
    out_dir = check_writable(out_dir)  # once the arguments are known good, before the runs take their minutes
    bar = tqdm(total=len(sequences) * len(specs) * len(set(views)), disable=not progress, file=sys.stderr,
               desc="segmentation", unit="run", dynamic_ncols=True)
    bins, grids = [], {}
    try:
        for seq in sequences:
            grids[seq.name] = run_bin(seq, views, specs, scale, voxel_size, heldout_every, probe, bar, bins)
        interrupted = False
    except KeyboardInterrupt:  # Ctrl-C: the runs that finished are reported, then the interrupt goes on
        interrupted = True
    bar.close()
    results = {"methods": [s.label for s in specs], "views": sorted(set(views)), "scale": scale,
               "heldout_every": heldout_every, "probe": probe,
               "probe_settings": {"steps": PROBE_STEPS, "pixels": PROBE_PIXELS, "weight_decay": PROBE_WEIGHT_DECAY,
                                  "seed": PROBE_SEED},
               "bins": [b for b in bins if b["runs"]], "mean": mean_runs(bins) if len(bins) > 1 and not interrupted else []}
    if interrupted:
        write_partial_segmentation_report({**results, "partial": True}, out_dir)
        raise KeyboardInterrupt
    write_segmentation_report(results, grids, out_dir)
    return results


# -- the report ------------------------------------------------------------------------------------
