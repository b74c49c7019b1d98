"""The segmentation experiment's report: results.json, results.md (the protocol and the table of
every capture, method and N), the mIoU-against-views plot and the label-map grids
(`eval.segmentation` computes what they show)."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .figures import _method_colours, _pyplot, _save, image_grid
from .report import EVALUATION_FIGURES, SEGMENTATION_FIGURES, _finite, _num, _table, remove_stale

TABLE_COLUMNS = (("fusion_miou", "label mIoU"), ("fusion_miou_covered", "label mIoU covered"),
                 ("fusion_accuracy", "label acc."), ("fusion_accuracy_covered", "label acc. covered"),
                 ("probe_miou", "probe mIoU"), ("probe_miou_covered", "probe mIoU covered"),
                 ("probe_accuracy", "probe acc."), ("probe_accuracy_covered", "probe acc. covered"),
                 ("client_probe_miou", "client-feature probe mIoU"), ("client_probe_miou_covered", "client-feature probe mIoU covered"))


def segmentation_table(runs: Sequence[Mapping]) -> list[str]:
    """Markdown rows: per capture, method and N, coverage and the metrics of `TABLE_COLUMNS` that
    any run has."""
    columns = [(k, h) for k, h in TABLE_COLUMNS if any(r.get(k) is not None for r in runs)]
    rows = [[r["dataset"], r["method"], str(r["views"]), _num(r["coverage"], 3), *(_num(r.get(k), 3) for k, _ in columns)]
            for r in runs]
    return _table(["capture", "method", "N", "coverage", *(h for _, h in columns)], rows)


def segmentation_markdown(results: Mapping) -> str:
    """results.md: the protocol and the table (every capture, then the mean over captures); an
    interrupted experiment's says so and holds the runs that finished."""
    partial = ["The run was interrupted: these are the runs (one method at one N of a capture) that finished "
               "before it; the mean over captures and the figures of a full report are left out.", ""]
    lines = ["# Segmentation" + (": partial (interrupted)" if results.get("partial") else ""), "",
             *(partial if results.get("partial") else []),
             f"Held out: one frame in {results['heldout_every']}, from position 1; the N inputs spread evenly over the rest. "
             f"Images at scale {results['scale']:g}; label maps looked up nearest at the render's pixels.",
             "Label mIoU / acc.: the argmax of the fused label scores splatted at the held-out cameras. Probe: a linear "
             f"classifier (multinomial logistic regression, L-BFGS, {results['probe_settings']['steps']} iterations, at most "
             f"{results['probe_settings']['pixels']} pixels, seed {results['probe_settings']['seed']}) trained on the feature "
             "splats at the input cameras against their labels, tested on the feature splats at the held-out cameras.",
             "Covered: pixels with accumulated opacity >= 0.5, the only ones given a label. All pixels: uncovered ones count "
             "as wrong (a miss of the true class, no false positive). mIoU: mean IoU over the classes present in the ground "
             "truth or the prediction; one confusion matrix per capture, method and N over all its held-out frames.", ""]
    for b in results["bins"]:
        lines += [f"- {b['dataset']}: {b['frames']} frames, labels {b['label_ids']}, images {b['image_size'][0]}x"
                  f"{b['image_size'][1]}, voxel {b['voxel_size']:g} m, held out {b['heldout']}, inputs {b['inputs']}"
                  + (", client features" if b["client_features"] else "")]
    lines += ["", *segmentation_table([r for b in results["bins"] for r in b["runs"]] + list(results["mean"])), ""]
    return "\n".join(lines)


def plot_segmentation(results: Mapping, path: Path) -> None:
    """mIoU vs input views per method: label fusion and probe, all pixels and covered; the mean
    over captures when there are several, else the one capture."""
    plt = _pyplot()
    runs = results["mean"] or results["bins"][0]["runs"]
    panels = [(k, h) for k, h in TABLE_COLUMNS if "miou" in k and any(r.get(k) is not None for r in runs)]
    colours = _method_colours(plt, results["methods"])
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 4), squeeze=False)
    for ax, (key, title) in zip(axes[0], panels):
        for m in results["methods"]:
            pts = sorted((r["views"], r[key]) for r in runs if r["method"] == m and r.get(key) is not None)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker="o", label=m, color=colours[m])
        ax.set_xscale("log", base=2)
        ax.set_xticks(results["views"], [str(v) for v in results["views"]])
        ax.set(title=title, xlabel="input views N", ylabel="mIoU", ylim=(0, 1))
        ax.grid(alpha=0.3)
    fig.suptitle("segmentation: " + ("mean over " + ", ".join(b["dataset"] for b in results["bins"])
                                     if results["mean"] else results["bins"][0]["dataset"]))
    _save(fig, axes[0][-1], path)
    plt.close(fig)


def write_segmentation_report(results: Mapping, grids: Mapping[str, Mapping[int, Mapping[str, Sequence[np.ndarray]]]],
                              out_dir: Path) -> list[Path]:
    """results.json, results.md, miou_vs_views.png and grid_{capture}_N{N}.png (image, ground truth
    and every method's label map at a few held-out frames); returns the paths."""
    written = _write_tables(results, out_dir) + [out_dir / "miou_vs_views.png"]
    plot_segmentation(results, written[2])
    for name, by_views in grids.items():
        for n, columns in by_views.items():
            written.append(out_dir / f"grid_{name}_N{n}.png")
            image_grid(columns).save(written[-1])
    remove_stale(out_dir, ["grid_*_N*.png", *EVALUATION_FIGURES], written)
    return written


def write_partial_segmentation_report(results: Mapping, out_dir: Path) -> list[Path]:
    """results.json and results.md of an interrupted experiment (`segmentation_markdown` says so); an
    earlier run's figures are removed so that none stand beside these numbers."""
    written = _write_tables(results, out_dir)
    remove_stale(out_dir, [*SEGMENTATION_FIGURES, *EVALUATION_FIGURES], written)
    return written


def _write_tables(results: Mapping, out_dir: Path) -> list[Path]:  # results.json and results.md
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / "results.json", out_dir / "results.md"]
    written[0].write_text(json.dumps(_finite(results), indent=1))
    written[1].write_text(segmentation_markdown(results))
    return written
