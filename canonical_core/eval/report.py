"""Writing the evaluation: results.json, results.md (tables), and the PNG plots and image grids that
`figures` draws.

Files in the output folder:
- ``results.json``: the results dict (non-finite numbers written as null);
- ``results.md``: protocol, main table, PSNR pivots (all / covered, common pixels), the first method's
  leads over the others, each method's worst step as views are added, noise tables, mixed-quality
  inputs, extrapolation, stability;
- ``psnr_vs_views.png``: PSNR (all pixels, covered pixels, common pixels, common pixels near depth
  edges and elsewhere, extrapolation) vs input views per method;
- ``noise_psnr.png``: PSNR vs depth-noise level per method, one panel per N (with --noise);
- ``stability.png``: feature-splat cosine to the reference vs input views (when computed);
- ``grid_N{N}.png``: ground truth and every method at a few held-out frames, clean depth.

Figures of an earlier run in the folder that this one does not write (the segmentation experiment's,
a grid of an N not run now) are removed.
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .figures import image_grid, plot_noise, plot_stability, plot_views
from .metrics import COVERAGE_THRESHOLD, DEPTH_TOLERANCE_VOXELS, EDGE_JUMP, EDGE_RADIUS
from .protocol import EXTRAPOLATION_RATIO, HELDOUT_COUNT

# how Gaussians' renders were scored (`rendering.render`'s colour modes); results without the key predate the choice
COLOUR_MODES = {
    "normalised": "Gaussians rendered in normalised colour: each drawn pixel shows sum(w c) / sum(w), the expected colour "
                  "of the surface its ray hits (as Open3D's ray cast shows its hits), black where nothing is drawn.",
    "composited": "Gaussians rendered in composited colour: the 3DGS blend over black, so partly covered pixels darken.",
}


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _num(value, digits: int = 2, suffix: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}f}{suffix}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|",
            *("| " + " | ".join(r) + " |" for r in rows)]


def _relative(value, clean) -> str:
    if value is None or clean in (None, 0):
        return "-"
    return f"{100.0 * (value - clean) / abs(clean):+.1f} %"


def _metric_rows(runs: Sequence[dict]) -> list[list[str]]:
    return [[r["method"], str(r["views"]), _num(r["psnr"]), _num(r["psnr_covered"]), _num(r["psnr_common"]), _num(r["coverage"], 3),
             _num(r["psnr_ceiling"]), _num(r["ssim"], 3), _num(r["depth_agreement"], 3), "-" if r["gaussians"] is None else str(r["gaussians"]), _num(r["fold_ms"], 0),
             _num(r["render_ms"], 0)] for r in runs]


_METRIC_HEADER = ["method", "N", "PSNR dB", "PSNR covered dB", "PSNR common dB", "coverage", "ceiling dB", "SSIM", "depth agree", "Gaussians", "fold+decode ms", "render ms"]


# The paper's aggregation ablations, the full rule first, and the metrics their order is read on
ABLATIONS = ("canonical", "no_reliability", "no_similarity", "average")
ORDER_METRICS = (("psnr", "PSNR"), ("psnr_covered", "covered PSNR"), ("ssim", "SSIM"), ("depth_agreement", "depth agree"))


def _settings_of(label: str) -> tuple[str, str] | None:
    """(ablation, settings) of a run's method label (``average:model=P`` -> ``("average", "model=P")``),
    or None for a method outside `ABLATIONS`."""
    name, _, settings = label.partition(":")
    return (name, settings) if name in ABLATIONS else None


def ablation_order(runs: Sequence[dict]) -> list[list[str]]:
    """Rows (settings, metric, N, the ablations best first, the full rule's rank, `average`'s rank)
    over ``runs`` of one condition (clean, or the mixed-quality run), for every N where all of
    `ABLATIONS` ran with the same settings (none: "defaults"; e.g. ``model=PATH`` for a trained
    decoder, each group ranked on its own); ties keep `ABLATIONS`' order. The paper's order is the
    full rule first and `average` last or near it."""
    value = {}
    for r in runs:
        if (parsed := _settings_of(r["method"])) is not None:
            value[parsed[1], parsed[0], r["views"]] = r
    rows = []
    for settings in dict.fromkeys(s for s, _, _ in value):
        views = sorted({n for (s, _, n) in value if s == settings and all((s, a, n) in value for a in ABLATIONS)})
        for key, label in ORDER_METRICS:
            for n in views:
                scores = {a: _finite(value[settings, a, n].get(key)) for a in ABLATIONS}
                if any(v is None for v in scores.values()):
                    continue
                order = sorted(ABLATIONS, key=lambda a: -scores[a])  # stable: ties in ABLATIONS' order
                rank = {a: f"{order.index(a) + 1} of {len(order)}" for a in ("canonical", "average")}
                rows.append([settings or "defaults", label, str(n), " > ".join(order), rank["canonical"], rank["average"]])
    return rows


def _difference(a, b, digits: int) -> str:
    a, b = _finite(a), _finite(b)
    return "-" if a is None or b is None else f"{a - b:+.{digits}f}"


# a method's lead over a peer: (the run's key, its column, digits)
LEAD_METRICS = (("psnr_common", "PSNR common dB", 2), ("ssim", "SSIM", 3), ("psnr", "PSNR dB", 2),
                ("psnr_covered", "PSNR covered dB", 2), ("depth_agreement", "depth agree", 3))


def leads(runs: Sequence[dict], methods: Sequence[str]) -> list[list[str]]:
    """Rows (peer, N, the lead of ``methods[0]`` over the peer in each of `LEAD_METRICS`) for every
    other method of ``runs`` (one condition) and every N both ran: positive where the first method is
    ahead. What a comparison with a peer is read on, without subtracting columns by hand."""
    by_key = {(r["method"], r["views"]): r for r in runs}
    first = methods[0]
    return [[peer, str(n), *(_difference(by_key[first, n].get(key), by_key[peer, n].get(key), digits)
                             for key, _, digits in LEAD_METRICS)]
            for peer in methods[1:] for n in sorted({r["views"] for r in runs})
            if (first, n) in by_key and (peer, n) in by_key]


def view_steps(runs: Sequence[dict], methods: Sequence[str]) -> list[list[str]]:
    """Rows (method, the worst step of PSNR on all pixels and on covered pixels from one N to the next,
    depth agreement at the smallest N -> at the largest) over ``runs`` of one condition: whether more
    views make each method better. A step is the next N's value minus this N's, the worst the lowest:
    negative where some N falls below the one before."""
    rows = []
    for m in methods:
        mine = sorted((r for r in runs if r["method"] == m), key=lambda r: r["views"])
        if len(mine) < 2:
            continue
        steps = []
        for key in ("psnr", "psnr_covered"):
            values = [_finite(r.get(key)) for r in mine]
            diffs = [b - a for a, b in zip(values, values[1:]) if a is not None and b is not None]
            steps.append(f"{min(diffs):+.2f}" if diffs else "-")
        agree = f"{_num(_finite(mine[0].get('depth_agreement')), 3)} -> {_num(_finite(mine[-1].get('depth_agreement')), 3)}"
        rows.append([m, *steps, agree])
    return rows


def markdown(results: Mapping) -> str:
    """results.md: the protocol and every table."""
    views = sorted(int(k) for k in results["inputs"])
    methods = results["methods"]
    clean = [r for r in results["runs"] if r["noise"] == 0]
    by_key = {(r["method"], r["views"], r["noise"]): r for r in results["runs"]}
    width, height = results["image_size"]
    lines = [
        f"# Evaluation: {results['dataset']}",
        "",
        f"{results['frames']} frames, images {width}x{height} (scale {results['scale']:g}), voxel size {results['voxel_size']:g}.",
        f"Metrics are means over the held-out frames; background black; covered = accumulated alpha >= {COVERAGE_THRESHOLD:g};",
        COLOUR_MODES[results.get("colour", "composited")],
        f"depth agree = share of covered pixels with sensor depth whose rendered depth is within {DEPTH_TOLERANCE_VOXELS:g} "
        "voxels of it (Gaussians: the median depth, where a pixel's transmittance falls below 1/2; Open3D: its ray cast's hit).",
        "ceiling = the all-pixel PSNR the method's drawing allows (the pixels it shows in full colour exact, the rest black: "
        "every drawn pixel in normalised colour, the covered ones in composited): above it needs more coverage, not better colours.",
        "common = PSNR over the pixels that every method of the table covers (share of the image in the pivot below): "
        "methods of unequal coverage judged on the same pixels.",
        f"Inputs for N views: round(linspace(0, n - 1, N)). Held-out: for each target in linspace(2, n - 3, {HELDOUT_COUNT}) "
        "the nearest position that is not an input for any N here and not already held out (ties to the lower one).",
        "",
        "Held-out positions (frame ids): " + ", ".join(f"{p} ({i})" for p, i in zip(results["heldout"], results["heldout_ids"])),
        "",
        *(f"- inputs N={n}: {results['inputs'][str(n)]}" for n in views),
    ]
    if results["skipped"]:
        lines += ["", *(f"- skipped `{m}`: {why}" for m, why in results["skipped"].items())]

    lines += ["", "## Held-out views, clean depth", "", *_table(_METRIC_HEADER, _metric_rows(
        sorted(clean, key=lambda r: (r["views"], methods.index(r["method"])))))]
    lines += ["", "## PSNR all pixels / covered pixels (dB) vs input views", "", *_table(
        ["method", *(f"N={n}" for n in views)],
        [[m, *(f"{_num(by_key[m, n, 0.0]['psnr'])} / {_num(by_key[m, n, 0.0]['psnr_covered'])}" for n in views)]
         for m in methods])]
    share = {n: by_key[methods[0], n, 0.0]["common_coverage"] for n in views}
    lines += ["", "## PSNR on the pixels every method covers (dB) vs input views", "", *_table(
        ["method", *(f"N={n} ({_num(share[n], 3)} of the image)" for n in views)],
        [[m, *(_num(by_key[m, n, 0.0]["psnr_common"]) for n in views)] for m in methods])]
    if all(by_key[m, n, 0.0].get("psnr_edge") is not None for m in methods for n in views):  # needs sensor depth
        edge_share = {n: by_key[methods[0], n, 0.0]["edge_share"] for n in views}
        lines += ["", "## PSNR on the common pixels near depth edges / elsewhere (dB) vs input views", "",
                  f"edge = the common pixels within {EDGE_RADIUS} pixels of a depth edge of the held-out frame's sensor depth "
                  f"(a jump to a neighbour over {EDGE_JUMP:.0%} of the depth, or a hole; share of the common pixels in the "
                  "header); flat = the rest. Speckle at depth edges shows in the first number, noisy surfaces in the second.",
                  "", *_table(["method", *(f"N={n} ({_num(edge_share[n], 3)} edge)" for n in views)],
                              [[m, *(f"{_num(by_key[m, n, 0.0]['psnr_edge'])} / {_num(by_key[m, n, 0.0]['psnr_flat'])}"
                                     for n in views)] for m in methods])]
    lead_rows = leads(clean, methods)
    if lead_rows:
        lines += ["", f"## {methods[0]} against the other methods, clean depth", "",
                  f"The lead of {methods[0]} over each other method at each N (its value minus the other's: positive where "
                  f"{methods[0]} is ahead).", "", *_table(["method", "N", *(label for _, label, _ in LEAD_METRICS)], lead_rows)]
    step_rows = view_steps(clean, methods)
    if step_rows:
        lines += ["", "## More views: the worst step from one N to the next, clean depth", "",
                  "Each method's PSNR at the next N minus at this N, the lowest over the steps (negative: some N falls "
                  "below the one before), and its depth agreement at the smallest and the largest N.", "",
                  *_table(["method", "PSNR dB, worst step", "PSNR covered dB, worst step",
                           f"depth agree, N={views[0]} -> N={views[-1]}"], step_rows)]
    lines += ["", "## PSNR on the pixels the smallest N covers (dB) vs input views", "",
              f"Each method on the pixels its own N={views[0]} scene covered (those still covered): whether more views "
              "make the scene better where it was already drawn. Covered PSNR also counts the pixels that added views "
              "draw for the first time.", "", *_table(
                  ["method", *(f"N={n}" for n in views)],
                  [[m, *(_num(by_key[m, n, 0.0].get("psnr_fixed")) for n in views)] for m in methods])]

    order_header = ["settings", "metric", "N", "best first", "canonical's rank", "average's rank"]
    order = ablation_order(clean)
    if order:
        lines += ["", "## Ablation order, clean depth (the paper's: the full rule first, `average` last or near it)", "",
                  *_table(order_header, order)]

    levels = results["noise_levels"]
    if levels:
        for metric, label in (("psnr", "PSNR dB"), ("ssim", "SSIM")):
            digits = 2 if metric == "psnr" else 3
            rows = []
            for m in methods:
                for n in views:
                    base = by_key[m, n, 0.0][metric]
                    rows.append([m, str(n), _num(base, digits), *(
                        f"{_num(by_key[m, n, lv][metric], digits)} ({_relative(by_key[m, n, lv][metric], base)})" for lv in levels)])
            lines += ["", f"## Depth noise: {label} (relative change from clean)", "",
                      "sigma = level x the frame's median depth, zero-mean Gaussian, fixed seeds.", "", *_table(
                          ["method", "N", "clean", *(f"{lv:g}" for lv in levels)], rows)]

    mixed = results["mixed_noise"]
    if mixed is not None:
        lines += ["", f"## Mixed-quality inputs: depth noise {mixed['level']:g} on every other input view", "",
                  "The 2nd, 4th, ... input views noisy, the others clean: evidence of uneven quality, which "
                  "reliability weighting is for.", "", *_table(_METRIC_HEADER, _metric_rows(
                      sorted(mixed["runs"], key=lambda r: (r["views"], methods.index(r["method"])))))]
        mixed_order = ablation_order(mixed["runs"])
        if mixed_order:
            lines += ["", "Ablation order on the mixed-quality inputs:", "", *_table(order_header, mixed_order)]

    extra = results["extrapolation"]
    if extra is not None:
        lines += ["", f"## Extrapolation (targets span {EXTRAPOLATION_RATIO - 1:.0%} more than the inputs), clean depth", "",
                  *(f"- inputs N={k}: {v} (target span / input span = {extra['span_ratio'][k]:.2f})" for k, v in extra["inputs"].items()),
                  "", *_table(_METRIC_HEADER, _metric_rows(
                      sorted(extra["runs"], key=lambda r: (r["views"], methods.index(r["method"])))))]
    else:
        lines += ["", "Extrapolation split: not run (disabled, or the sequence has too few free frames for it)."]

    if results["stability"]:
        counts = sorted(int(k) for k in results["stability_inputs"])
        cos = {(r["method"], r["views"]): r["cosine"] for r in results["stability"]}
        stab_methods = list(dict.fromkeys(r["method"] for r in results["stability"]))
        lines += ["", f"## Feature stability: mean cosine to the {counts[-1]}-view feature splat (covered pixels)", "",
                  *_table(["method", *(f"N={n}" for n in counts)], [[m, *(_num(cos[m, n], 3) for n in counts)] for m in stab_methods])]
    return "\n".join(lines) + "\n"


EVALUATION_FIGURES = ("psnr_vs_views.png", "noise_psnr.png", "stability.png", "grid_N*.png")
SEGMENTATION_FIGURES = ("miou_vs_views.png", "grid_*_N*.png")
"""The figures of each experiment: a report removes the other's from a folder the two share, so
that the folder shows one run only."""


class UnwritableFolder(ValueError):
    """An output folder that cannot be made or written; ``field`` names the argument that gave it and
    ``detail`` says the path and why, so that a command can name its own flag instead."""

    def __init__(self, field: str, detail: str):
        super().__init__(f"{field}: {detail}")
        self.field, self.detail = field, detail


def check_writable(folder: str | Path, field: str = "out_dir") -> Path:
    """Make ``folder`` (and its parents) and check that a file can be written in it; `UnwritableFolder`
    naming ``field`` otherwise. Called before a long run, which would otherwise fail only at the end
    when it writes its results (a path under a file, an existing file, a folder without write access)."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise UnwritableFolder(field, f"cannot write {folder}: {exc.strerror or exc}") from None
    return folder


def write_report(results: Mapping, grids: Mapping[int, Mapping[str, Sequence[np.ndarray]]], out_dir: Path) -> list[Path]:
    """Write every file listed in the module docstring; returns their paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "results.json", out_dir / "results.md", out_dir / "psnr_vs_views.png"]
    written[0].write_text(json.dumps(_finite(results), indent=1, allow_nan=False))
    written[1].write_text(markdown(results))
    plot_views(results, written[2])
    if results["noise_levels"]:
        written.append(out_dir / "noise_psnr.png")
        plot_noise(results, written[-1])
    if results["stability"]:
        written.append(out_dir / "stability.png")
        plot_stability(results, written[-1])
    for n, columns in grids.items():
        written.append(out_dir / f"grid_N{n}.png")
        image_grid(columns).save(written[-1])
    remove_stale(out_dir, [*EVALUATION_FIGURES, *SEGMENTATION_FIGURES], written)
    return written


def write_partial_report(results: Mapping, out_dir: Path) -> list[Path]:
    """results.json and results.md of an interrupted evaluation: the groups of runs that finished, in
    plain tables, under a note that says so. The pivots and figures need every method at every N, so
    none are drawn, and an earlier run's figures are removed so that none stand beside these numbers."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "results.json", out_dir / "results.md"]
    written[0].write_text(json.dumps(_finite(results), indent=1, allow_nan=False))
    methods = results["methods"]
    order = lambda runs: sorted(runs, key=lambda r: (r["views"], methods.index(r["method"])))  # noqa: E731
    lines = [f"# Evaluation on {results['dataset']}: partial (interrupted)", "",
             "The run was interrupted: these are the groups of runs (every method at one N) that finished before it. "
             "The comparisons across N and the figures of a full report are left out."]
    for level in [0.0, *results["noise_levels"]]:
        done = [r for r in results["runs"] if r["noise"] == level]
        if done:
            title = "clean depth" if level == 0 else f"depth noise {level:g}"
            lines += ["", f"## Held-out views, {title}", "", *_table(_METRIC_HEADER, _metric_rows(order(done)))]
    for key, title in (("mixed_noise", "Mixed-quality inputs"), ("extrapolation", "Extrapolation, clean depth")):
        done = (results[key] or {}).get("runs") or []
        if done:
            lines += ["", f"## {title}", "", *_table(_METRIC_HEADER, _metric_rows(order(done)))]
    written[1].write_text("\n".join(lines) + "\n")
    remove_stale(out_dir, [*EVALUATION_FIGURES, *SEGMENTATION_FIGURES], written)
    return written


def remove_stale(out_dir: Path, patterns: Sequence[str], written: Sequence[Path]) -> None:
    """Remove the files matching ``patterns`` that an earlier report into ``out_dir`` wrote and this
    one did not (a grid of an N not run now), so that the folder shows this run only."""
    for path in {p for pattern in patterns for p in out_dir.glob(pattern)} - set(written):
        path.unlink()
