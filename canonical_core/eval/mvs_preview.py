"""Pictures of estimated depth and its uncertainty, for looking at what the plane sweep did.

`write_depth_previews` estimates every frame of a capture from its best neighbours (as
`select_sources` picks them, among frames at most ``search`` indices away, with the sensor depth
withheld) and writes, per frame, colour-mapped PNGs with a legend (colour bar, tick values, unit):

    <frame_id>.depth.png         estimated depth, metres (black: no depth - no source sees the pixel)
    <frame_id>.uncertainty.png   U_pos, millimetres (black: no depth)
    <frame_id>.sensor.png        the frame's own sensor depth in the same colours, when it has one

One colour scale is used for the whole capture (fixed from the first frame, or given), so frames can
be compared. `colorize` and `legend_image` are reusable for other maps.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from ..evidence.mvs import DEFAULT_NUM_HYPOTHESES, depth_range_from_depth, estimate_depth_detailed
from ..evidence.source_views import DEFAULT_SCALE, SelectionRule, SourceView, select_sources
from ..frame import Frame
from .mvs_eval import compare_to_sensor, without_depth

# anchor colours (sRGB 0-255) of two perceptually ordered maps, interpolated linearly
DEPTH_COLOURS = np.array([(68, 1, 84), (72, 40, 120), (62, 74, 137), (49, 104, 142), (38, 130, 142),
                          (31, 158, 137), (53, 183, 121), (109, 205, 89), (180, 222, 44), (253, 231, 37)], np.float64)
UNCERTAINTY_COLOURS = np.array([(0, 0, 4), (40, 11, 84), (101, 21, 110), (159, 42, 99), (212, 72, 66),
                                (245, 125, 21), (250, 193, 39), (252, 255, 164)], np.float64)
MISSING_COLOUR = (0, 0, 0)
LEGEND_WIDTH = 110


def colorize(
    values: np.ndarray,  # [H, W]
    lo: float,
    hi: float,
    colours: np.ndarray = DEPTH_COLOURS,  # [C, 3] anchors, low to high
    valid: np.ndarray | None = None,  # [H, W] bool; default values > 0
) -> np.ndarray:  # [H, W, 3] uint8
    """Map values in [lo, hi] (clipped) through the anchor colours; invalid pixels get MISSING_COLOUR."""
    v = np.asarray(values, np.float64)
    if valid is None:
        valid = np.isfinite(v) & (v > 0)
    t = np.clip((np.nan_to_num(v) - lo) / max(hi - lo, 1e-12), 0.0, 1.0) * (len(colours) - 1)
    i0 = np.minimum(np.floor(t).astype(np.int64), len(colours) - 2)
    f = (t - i0)[..., None]
    rgb = colours[i0] * (1 - f) + colours[i0 + 1] * f
    out = np.rint(rgb).astype(np.uint8)
    out[~valid] = MISSING_COLOUR
    return out


def _font():
    try:
        return ImageFont.load_default(size=12)
    except TypeError:  # Pillow without FreeType sizes
        return ImageFont.load_default()


def legend_image(height: int, lo: float, hi: float, colours: np.ndarray, title: str, unit_scale: float = 1.0,
                 decimals: int = 2, note: str = "black: none") -> Image.Image:
    """A vertical colour bar (high at the top) with 5 tick values (value * unit_scale) and a title."""
    img = Image.new("RGB", (LEGEND_WIDTH, height), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    font = _font()
    top, bottom = 26, max(height - 24, 40)
    bar = np.linspace(hi, lo, max(bottom - top, 2))[:, None].repeat(18, 1)
    img.paste(Image.fromarray(colorize(bar, lo, hi, colours, valid=np.ones(bar.shape, bool))), (8, top))
    draw.text((4, 6), title, fill=(0, 0, 0), font=font)
    for k in range(5):
        frac = k / 4
        y = int(round(top + frac * (bottom - top - 1)))
        value = (hi - frac * (hi - lo)) * unit_scale
        draw.line([(26, y), (31, y)], fill=(0, 0, 0))
        draw.text((34, y - 6), f"{value:.{decimals}f}", fill=(0, 0, 0), font=font)
    draw.text((4, height - 18), note, fill=(0, 0, 0), font=font)
    return img


def _with_legend(rgb: np.ndarray, legend: Image.Image) -> Image.Image:
    h, w = rgb.shape[:2]
    out = Image.new("RGB", (w + legend.width, h), (255, 255, 255))
    out.paste(Image.fromarray(rgb), (0, 0))
    out.paste(legend, (w, 0))
    return out


def _safe_name(frame_id: str | None, index: int) -> str:
    name = frame_id if frame_id else f"frame-{index:06d}"
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def write_depth_previews(
    frames: Sequence[Frame],
    out_dir: str | Path,
    num_sources: int = 2,
    near: float | None = None,
    far: float | None = None,
    num_hypotheses: int = DEFAULT_NUM_HYPOTHESES,
    scale: float = DEFAULT_SCALE,
    depth_range: tuple[float, float] | None = None,
    max_uncertainty: float | None = None,
    typical_depth: float | None = None,
    search: int = 30,
    indices: Sequence[int] | None = None,
    rule: SelectionRule | None = None,
    progress: Callable[[], object] | None = None,
) -> list[dict]:
    """Estimate depth for frames of a capture and write colour-mapped PNGs with legends.

    Args:
        frames: the capture (e.g. a lazily loading `FrameSequence`); frames need no depth.
        out_dir: folder for the PNGs (created).
        num_sources: sources per frame, chosen by `select_sources` among the frames within ``search``
            indices (sensor depth of the reference is never used for the estimate).
        near, far: swept range (metres). By default derived from the first source's sensor depth
            when it has one (what a scene would already hold), else 0.1-10 m.
        depth_range: (lo, hi) of the depth colours, metres; default: the 2-98 % percentiles of the
            first estimated frame, kept for all frames.
        max_uncertainty: top of the U_pos colours, metres; default: the first frame's 95 % percentile.
        typical_depth: scene depth used to judge baselines (default: sqrt(near * far)).
        indices: which frames to write (default: all).
        progress: called once per frame done (written, or skipped for want of sources): a bar's step.

    Returns one dict per written frame: ``frame_id``, ``depth_png``, ``uncertainty_png``,
    ``sensor_png`` (or None), ``sources`` (frame ids), ``coverage`` (share of pixels with depth) and,
    when the frame has sensor depth, ``median_abs_rel``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n = len(frames)
    if n < 2:
        raise ValueError(f"frames: need at least 2 frames to estimate depth from other views, got {n}")
    cache: OrderedDict[int, Frame] = OrderedDict()
    views: OrderedDict[int, SourceView] = OrderedDict()

    def frame(i: int) -> Frame:
        if i not in cache:
            cache[i] = frames[i]
            if len(cache) > 2 * search + 2:
                cache.popitem(last=False)
        return cache[i]

    def view(i: int) -> SourceView:
        if i not in views:
            views[i] = SourceView.from_frame(without_depth(frame(i)), scale)
            if len(views) > 4 * (num_sources + 1):
                views.popitem(last=False)
        return views[i]

    results = []
    for i in (range(n) if indices is None else indices):
        ref = frame(i)
        others = [j for j in range(max(0, i - search), min(n, i + search + 1)) if j != i]
        if near is None or far is None:
            derived = None
            for j in others:
                if frame(j).depth is not None:
                    derived = depth_range_from_depth(frame(j).depth)
                    if derived:
                        break
            near, far = derived if derived else (near or 0.1, far or 10.0)
        z = typical_depth or math.sqrt(near * far)
        picked = [others[k] for k in select_sources(ref.camera, [frame(j).camera for j in others], k=num_sources,
                                                    depth=z, rule=rule)]
        if not picked:
            if progress is not None:
                progress()
            continue
        est = estimate_depth_detailed(without_depth(ref), [view(j) for j in picked], near, far, num_hypotheses,
                                      scale, reference=view(i))
        valid = est.depth > 0
        if depth_range is None:
            lo, hi = (np.percentile(est.depth[valid], [2, 98]) if valid.any() else (near, far))
            depth_range = (float(lo), float(max(hi, lo * 1.01)))
        if max_uncertainty is None:
            max_uncertainty = float(np.percentile(est.uncertainty[valid], 95)) if valid.any() else 0.1 * far
            max_uncertainty = max(max_uncertainty, 1e-4)
        lo, hi = depth_range
        name = _safe_name(ref.frame_id, i)
        H = ref.height
        depth_legend = legend_image(H, lo, hi, DEPTH_COLOURS, "depth [m]", 1.0, 2, "black: no depth")
        unc_legend = legend_image(H, 0.0, max_uncertainty, UNCERTAINTY_COLOURS, "U_pos [mm]", 1000.0,
                                  1 if max_uncertainty < 0.1 else 0, "black: no depth")
        depth_png, unc_png = out / f"{name}.depth.png", out / f"{name}.uncertainty.png"
        _with_legend(colorize(est.depth, lo, hi, DEPTH_COLOURS), depth_legend).save(depth_png)
        _with_legend(colorize(est.uncertainty, 0.0, max_uncertainty, UNCERTAINTY_COLOURS, valid=valid),
                     unc_legend).save(unc_png)
        record = {"frame_id": ref.frame_id, "depth_png": str(depth_png), "uncertainty_png": str(unc_png),
                  "sensor_png": None, "sources": [frame(j).frame_id for j in picked],
                  "coverage": float(valid.mean())}
        if ref.depth is not None:
            sensor = ref.depth.numpy()
            sensor_png = out / f"{name}.sensor.png"
            _with_legend(colorize(sensor, lo, hi, DEPTH_COLOURS), depth_legend).save(sensor_png)
            abs_rel, _, _ = compare_to_sensor(est.depth, est.uncertainty, sensor)
            record["sensor_png"] = str(sensor_png)
            record["median_abs_rel"] = float(np.median(abs_rel)) if abs_rel.size else math.nan
        results.append(record)
        if progress is not None:
            progress()
    return results
