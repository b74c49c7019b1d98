"""The evaluation's pictures: PNG plots of the scores against input views, depth noise and feature
stability (matplotlib, Agg), and image grids of held-out frames beside every method's render (Pillow).
`report.write_report` writes them beside the tables."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

GRID_TILE_WIDTH = 320  # pixels: tiles of the image grids are downscaled to at most this width
_HEADER = 18  # pixels: label band above each grid column


def require_matplotlib() -> None:
    """Raise early (before a long run) when the plotting dependency is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ImportError("matplotlib: the evaluation plots need the eval extra (pip install 'canonicalgs-fusion[eval]')") from None


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _series(runs: Sequence[dict], method: str, key: str, x: str = "views") -> tuple[list, list]:
    pts = sorted((r[x], r[key]) for r in runs if r["method"] == method and r[key] is not None)
    return [p[0] for p in pts], [p[1] for p in pts]


def _method_colours(plt, methods: Sequence[str]) -> dict[str, tuple]:
    """One colour per method, the same in every plot (tab20: eleven methods would wrap tab10's
    cycle and draw the first and the eleventh alike)."""
    cmap = plt.get_cmap("tab20")
    return {m: cmap(i % cmap.N) for i, m in enumerate(methods)}


def _save(fig, ax, path: Path) -> None:
    """Legend beside the last panel, not over its lines: every line of every panel, once (a line drawn
    only in another panel, as the coverage ceiling, is named too)."""
    lines: dict[str, object] = {}
    for panel in fig.axes:
        for handle, label in zip(*panel.get_legend_handles_labels()):
            lines.setdefault(label, handle)
    ax.legend(list(lines.values()), list(lines), fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=100, bbox_inches="tight")


def plot_views(results: Mapping, path: Path) -> None:
    """PSNR vs input views per method: all pixels, covered pixels, the pixels every method covers
    (and those of them near depth edges and away from them), the pixels each method covered at the
    smallest N, extrapolation (if run); the all-pixel panels
    also show the first method's coverage ceiling (dashed)."""
    plt = _pyplot()
    clean = [r for r in results["runs"] if r["noise"] == 0]
    panels = [("PSNR, all pixels", clean, "psnr"), ("PSNR, covered pixels", clean, "psnr_covered"),
              ("PSNR, pixels every method covers", clean, "psnr_common")]
    if all(r.get("psnr_edge") is not None for r in clean):  # none without sensor depth, or in older results
        panels += [("PSNR, common pixels near depth edges", clean, "psnr_edge"),
                   ("PSNR, common pixels away from edges", clean, "psnr_flat")]
    if all("psnr_fixed" in r for r in clean):  # results written before this figure existed lack it
        panels.append(("PSNR, pixels the smallest N covered", clean, "psnr_fixed"))
    if results["extrapolation"] is not None:
        panels.append(("PSNR, extrapolation", results["extrapolation"]["runs"], "psnr"))
    colours = _method_colours(plt, results["methods"])
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), squeeze=False)
    for ax, (title, runs, key) in zip(axes[0], panels):
        for m in results["methods"]:
            ax.plot(*_series(runs, m, key), marker="o", label=m, color=colours[m])
            if key == "psnr" and m == results["methods"][0]:  # the bound the first method's coverage sets
                ax.plot(*_series(runs, m, "psnr_ceiling"), linestyle="--", color=colours[m],
                        label=f"{m}: coverage ceiling")
        ax.set_xscale("log", base=2)
        ax.set_xticks(sorted(int(k) for k in results["inputs"]), [str(k) for k in sorted(int(k) for k in results["inputs"])])
        ax.set(title=title, xlabel="input views N", ylabel="dB")
        ax.grid(alpha=0.3)
    fig.suptitle(results["dataset"])
    _save(fig, axes[0][-1], path)
    plt.close(fig)


def plot_noise(results: Mapping, path: Path) -> None:
    """PSNR vs depth-noise level per method (0 = clean), one panel per N."""
    plt = _pyplot()
    views = sorted(int(k) for k in results["inputs"])
    colours = _method_colours(plt, results["methods"])
    fig, axes = plt.subplots(1, len(views), figsize=(4.5 * len(views), 4), squeeze=False)
    for ax, n in zip(axes[0], views):
        runs = [r for r in results["runs"] if r["views"] == n]
        for m in results["methods"]:
            ax.plot(*_series(runs, m, "psnr", x="noise"), marker="o", label=m, color=colours[m])
        ax.set(title=f"N={n}", xlabel="depth noise sigma / median depth", ylabel="PSNR dB")
        ax.grid(alpha=0.3)
    _save(fig, axes[0][-1], path)
    plt.close(fig)


def plot_stability(results: Mapping, path: Path) -> None:
    """Feature-splat cosine to the reference vs input views per method."""
    plt = _pyplot()
    colours = _method_colours(plt, results["methods"])
    fig, ax = plt.subplots(figsize=(6, 4))
    for m in dict.fromkeys(r["method"] for r in results["stability"]):
        ax.plot(*_series(results["stability"], m, "cosine"), marker="o", label=m, color=colours[m])
    ax.set(title="feature stability", xlabel="input views N", ylabel="mean cosine to the reference splat")
    ax.grid(alpha=0.3)
    _save(fig, ax, path)
    plt.close(fig)


_LABEL_MARGIN = 4  # pixels: a grid label's inset from its column's left edge, and the gap kept on its right


def fit_label(label: str, font, width: int) -> str:
    """``label`` as it fits a grid column ``width`` pixels wide in ``font`` (margins kept): a
    ``model=`` setting's path shown by its file name (the folders say nothing the name does not), then,
    where it is still too wide, the text cut and ended with "..."; a label that fits is kept as it is.
    Without this a long label runs under its neighbours' and both become unreadable."""
    room = width - 2 * _LABEL_MARGIN
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength
    if measure(label, font=font) <= room:
        return label
    label = ":".join(f"model={Path(part[6:]).name}" if part.startswith("model=") else part for part in label.split(":"))
    if measure(label, font=font) <= room:
        return label
    while label and measure(label + "...", font=font) > room:
        label = label[:-1]
    return label + "..." if label or measure("...", font=font) <= room else ""


def image_grid(columns: Mapping[str, Sequence[np.ndarray]]) -> Image.Image:
    """Columns of uint8 [H, W, 3] images (one row per held-out frame) under their names, each name
    fitted to its column (`fit_label`)."""
    names = list(columns)
    h, w = columns[names[0]][0].shape[:2]
    factor = min(1.0, GRID_TILE_WIDTH / w)
    tw, th = max(1, round(w * factor)), max(1, round(h * factor))
    rows = max(len(v) for v in columns.values())
    canvas = Image.new("RGB", (tw * len(names), _HEADER + th * rows), "white")
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default()
    for c, name in enumerate(names):
        draw.text((c * tw + _LABEL_MARGIN, 3), fit_label(name, font, tw), fill="black", font=font)
        for r, img in enumerate(columns[name]):
            canvas.paste(Image.fromarray(img).resize((tw, th), Image.BOX), (c * tw, _HEADER + r * th))
    return canvas
