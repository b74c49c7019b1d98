"""Defaults chosen across captures: setting variants scored on every capture, chosen leave-one-capture-out.

A default tuned on one capture absorbs that capture's sensor, depth range and voxel size. Here each
variant (a few `SceneConfig` settings changed from the defaults) is scored on every capture with the
evaluation's own protocol (`protocol.interpolation_split`, `run.score`): per N, all-pixel and
covered PSNR and depth agreement on the held-out frames. A capture's *objective* for a variant is the
mean over N of (all-pixel + covered PSNR) / 2, minus the default's: the change in dB.

Leave-one-capture-out: for each group of captures (captures of one sensor and place form a group, so
that a held-out group teaches nothing through its twin), the variant with the best mean objective
over the *other* groups is chosen, and its objective on the held-out group is what that choice is
worth on a capture it never saw. A default changes only where the choice is the same in every fold
and helps every held-out group.

Run: ``python -m canonical_core.eval.tuning --out docs/eval/tuning`` (results.json, results.md and a
PNG of the objectives).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..config import DEFAULT_FAMILY
from ..datasets import load_dataset
from ..frame import resize_frame
from ..scene import Scene, SceneConfig
from .methods import SplatModel
from .protocol import interpolation_split
from .report import UnwritableFolder, check_writable
from .run import default_voxel_size, score

VIEWS = (2, 4, 8, 16)


@dataclass(frozen=True)
class Variant:
    """A name and the `SceneConfig` settings it changes (groups as dicts, e.g. ``{"sensor": {...}}``)."""

    name: str
    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Capture:
    """A capture folder (any `load_dataset` layout) and the group it belongs to for leave-one-out."""

    path: str
    group: str


DEFAULT = Variant("default")


def default_of(path: str):
    """The default value of a knob (``group.name`` or a top-level name) in a new `SceneConfig`; a
    sensor value is the default family's (what `auto` gives every capture here: `bench/sensor_families.py`)."""
    value = SceneConfig(voxel_size=1.0)
    value = value.replace(sensor=value.sensor.with_preset(DEFAULT_FAMILY))
    for part in path.split("."):
        value = getattr(value, part)
    return value


def knob_variants(path: str, values: Sequence) -> tuple[Variant, ...]:
    """Variants setting one knob to each of ``values`` but its default (that one is `DEFAULT`)."""
    def settings(value) -> dict:
        group, _, name = path.rpartition(".")
        return {group: {name: value}} if group else {name: value}
    return tuple(Variant(f"{path}={v:g}", settings(v)) for v in values if v != default_of(path))


# each knob's values (the current default is skipped: it is DEFAULT)
KNOBS = {
    "sensor.registration_px": (0.0, 2.0, 4.0, 8.0),
    "sensor.edge_weight": (0.5, 1.0, 2.0),
    "free_space.margin": (0.0, 0.25, 0.5, 1.0, 2.0, 4.0),
    "free_space.dominance": (1.0, 2.0, 4.0),
    "free_space.sigmas": (3.0, 5.0, 8.0),
    "free_space.cell": (2, 4, 8),
    # from 3 up: a fully supported surface must stay at least 95 % opaque (sigmoid(3)); flatter lines
    # score higher in normalised colour only by letting renders blend through surfaces
    "decoder.opacity_slope": (3.0, 5.0, 10.0, 30.0, 90.0),
    "sh_degree": (0, 1),
    "sensor.weight_floor": (0.0, 0.5, 1.0),
    # metres: depth sensors of the RealSense class return no depth, or wrong depth, below about 0.2 m
    "range.near": (0.05, 0.1, 0.15, 0.2, 0.25, 0.3),
}
VARIANTS = (DEFAULT, *(v for path, values in KNOBS.items() for v in knob_variants(path, values)))


def knob_of(name: str) -> str | None:
    """The knob a variant name sets (``None`` for the default and for joint variants)."""
    path, sep, _ = name.partition("=")
    return path if sep and path in KNOBS else None

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
CAPTURES = (
    Capture(str(DATA / "realsense_shelf"), "realsense_shelf"),
    Capture(str(DATA / "hololens_office"), "hololens_office"),
    Capture(str(DATA / "apc_bins" / "bin_labels"), "apc_bins"),
    Capture(str(DATA / "apc_bins" / "bin_mask"), "apc_bins"),
    Capture(str(DATA / "sun3d_studyroom"), "sun3d_studyroom"),  # Kinect-class: flying pixels, quantised far depth
)


def allowed_views(n: int, views: Sequence[int] = VIEWS) -> tuple[int, ...]:
    """The longest prefix of ``views`` whose protocol split fits a sequence of ``n`` frames.

    Example:
        >>> allowed_views(15), allowed_views(50)
        ((2, 4), (2, 4, 8, 16))
    """
    for k in range(len(views), 0, -1):
        try:
            interpolation_split(n, views[:k])
            return tuple(views[:k])
        except ValueError:
            continue
    raise ValueError(f"n: a sequence of {n} frames allows no split for views {list(views)}")


def score_capture(capture: Capture, variants: Sequence[Variant], views: Sequence[int] = VIEWS, scale: float = 1.0,
                  bar: tqdm | None = None) -> dict:
    """Every variant on one capture (images downscaled by ``scale``, the voxel size following the
    evaluation's rule): per variant and N, the held-out metrics of `run.score`."""
    sequence = load_dataset(capture.path)
    views = allowed_views(len(sequence), views)
    split = interpolation_split(len(sequence), views)
    frames = {p: resize_frame(sequence[p], scale) for p in sorted(set(split.heldout).union(*split.inputs.values()))}
    targets = [frames[p] for p in split.heldout]
    voxel = default_voxel_size([frames[p] for p in split.inputs[max(views)]])
    rows = {}
    for variant in variants:
        config = SceneConfig(voxel_size=voxel, **variant.settings)
        per_n = {}
        for n_views, inputs in split.inputs.items():
            scene = Scene(config)
            for p in inputs:
                scene.fold(frames[p])
            metrics = score(SplatModel(scene.decode()), targets, voxel).metrics
            per_n[n_views] = {k: metrics[k] for k in ("psnr", "psnr_covered", "coverage", "depth_agreement", "ssim")}
            if bar is not None:
                bar.update()
        rows[variant.name] = per_n
    return {"capture": sequence.name, "path": capture.path, "group": capture.group, "voxel_size": voxel, "scale": scale,
            "views": list(views), "variants": rows}


def objective(per_n: Mapping) -> float:
    """Mean over N of (all-pixel + covered PSNR) / 2, in dB."""
    return float(np.mean([(m["psnr"] + m["psnr_covered"]) / 2 for m in per_n.values()]))


def agreement(per_n: Mapping) -> float:
    """Mean over N of held-out depth agreement."""
    return float(np.mean([m["depth_agreement"] for m in per_n.values()]))


def group_changes(captures: Sequence[dict], measure=objective) -> dict[str, dict[str, float]]:
    """{group: {variant: measure - the default's}}, averaged over the group's captures."""
    out: dict[str, dict[str, list[float]]] = {}
    for c in captures:
        base = measure(c["variants"][DEFAULT.name])
        for name, per_n in c["variants"].items():
            out.setdefault(c["group"], {}).setdefault(name, []).append(measure(per_n) - base)
    return {g: {name: float(np.mean(v)) for name, v in rows.items()} for g, rows in out.items()}


def leave_one_capture_out(deltas: Mapping[str, Mapping[str, float]], candidates: Sequence[str] | None = None) -> list[dict]:
    """Per held-out group: among ``candidates`` (default: every variant; the default is always one),
    the variant with the best mean change over the other groups (ties to the default, then to the
    first listed), that mean, and the change it makes on the held-out group.

    Example:
        >>> d = {"a": {"default": 0.0, "x": 0.5}, "b": {"default": 0.0, "x": 0.3}, "c": {"default": 0.0, "x": -0.1}}
        >>> [(r["held_out"], r["chosen"], r["held_out_change"]) for r in leave_one_capture_out(d)]
        [('a', 'x', 0.5), ('b', 'x', 0.3), ('c', 'x', -0.1)]
    """
    groups = list(deltas)
    if len(groups) < 2:
        raise ValueError(f"deltas: leave-one-out needs at least two groups, got {groups}")
    names = list(next(iter(deltas.values())))
    names = [n for n in names if n == DEFAULT.name or candidates is None or n in candidates]
    rows = []
    for held in groups:
        train = [g for g in groups if g != held]
        mean = {name: float(np.mean([deltas[g][name] for g in train])) for name in names}
        best = max(names, key=lambda name: (round(mean[name], 9), name == DEFAULT.name, -names.index(name)))
        rows.append({"held_out": held, "chosen": best, "train_change": mean[best], "held_out_change": deltas[held][best]})
    return rows


AGREEMENT_SLACK = 0.005  # a candidate may not lower any group's mean depth agreement by more than this


def choose_per_knob(deltas: Mapping[str, Mapping[str, float]],
                    agreement_changes: Mapping[str, Mapping[str, float]] | None = None) -> dict[str, dict]:
    """Leave-one-capture-out for each knob over its own values; a knob's value is *chosen* (a new
    default) only when every fold picks the same non-default value and it helps every held-out group.
    With ``agreement_changes`` (`group_changes` of `agreement`), values that lower some group's depth
    agreement by more than ``AGREEMENT_SLACK`` are not candidates: PSNR bought with floaters or
    see-through surfaces is not a better default.

    Example:
        >>> d = {g: {"default": 0.0, "free_space.margin=1": m, "sh_degree=0": s}
        ...      for g, m, s in (("a", 0.2, 0.3), ("b", 0.1, -0.2), ("c", 0.05, 0.1))}
        >>> {k: v["chosen"] for k, v in choose_per_knob(d).items()}
        {'free_space.margin': 'free_space.margin=1', 'sh_degree': None}
        >>> worse = {g: {"default": 0.0, "free_space.margin=1": -0.01, "sh_degree=0": 0.0} for g in d}
        >>> {k: v["chosen"] for k, v in choose_per_knob(d, worse).items()}
        {'free_space.margin': None, 'sh_degree': None}
    """
    names = list(next(iter(deltas.values())))
    out = {}
    for knob in dict.fromkeys(k for n in names if (k := knob_of(n))):
        candidates = [n for n in names if knob_of(n) == knob and (agreement_changes is None or all(
            agreement_changes[g][n] >= -AGREEMENT_SLACK for g in agreement_changes))]
        folds = leave_one_capture_out(deltas, candidates)
        picks = {r["chosen"] for r in folds}
        consistent = len(picks) == 1 and DEFAULT.name not in picks and all(r["held_out_change"] > 0 for r in folds)
        out[knob] = {"folds": folds, "chosen": picks.pop() if consistent else None}
    return out


def joint_variant(choices: Mapping[str, dict], variants: Sequence[Variant]) -> Variant | None:
    """One variant setting every chosen knob (``None`` when no knob was chosen)."""
    by_name = {v.name: v for v in variants}
    chosen = [by_name[c["chosen"]] for c in choices.values() if c["chosen"]]
    if not chosen:
        return None
    settings: dict = {}
    for v in chosen:
        for key, value in v.settings.items():
            if isinstance(value, dict):
                settings.setdefault(key, {}).update(value)
            else:
                settings[key] = value
    return Variant("joint: " + ", ".join(v.name for v in chosen), settings)


def _fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:+.{digits}f}"


def write_report(results: dict, out: Path) -> None:
    """results.json, results.md (the tables) and objectives.png (change per variant and capture group)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    deltas, knobs, captures = results["group_changes"], results["knobs"], results["captures"]
    groups, names = list(deltas), list(next(iter(deltas.values())))
    lines = ["# Defaults across captures: leave-one-capture-out", "",
             "Each variant changes the named settings from the defaults; objective = mean over N of "
             "(all-pixel + covered PSNR) / 2 on the held-out frames of the evaluation protocol; the tables "
             "give its change from the default in dB (captures of one group averaged).", "",
             "Made by `" + results["command"] + "`" + (f"; decided by `{results['decided_by']}`" if results.get("decided_by") else "")
             + ". \"default\" is the defaults of the code that ran.", "",
             "| capture | group | N | image scale | voxel size |", "|---|---|---|---|---|"]
    lines += [f"| {c['capture']} | {c['group']} | {', '.join(map(str, c['views']))} | {c['scale']:g} | {c['voxel_size']:g} |"
              for c in captures]
    lines += ["", "## Change of the objective (dB) per variant and capture group", "",
              "| variant | " + " | ".join(groups) + " | mean |", "|---|" + "---|" * (len(groups) + 1)]
    for name in names:
        values = [deltas[g][name] for g in groups]
        lines.append(f"| {name} | " + " | ".join(_fmt(v) for v in values) + f" | {_fmt(float(np.mean(values)))} |")
    lines += ["", "## Leave-one-capture-out, per knob", "",
              "Per knob, over its values and the default: the value best on the other groups, and what it "
              "changes on the held-out group. A value becomes the default only when every fold picks it and "
              "it helps every held-out group; values that lower some group's depth agreement by more than "
              f"{AGREEMENT_SLACK} are not candidates.", "",
              "| knob | held-out group | chosen on the others | change on the others | change on the held-out group |",
              "|---|---|---|---|---|"]
    for knob, choice in knobs.items():
        lines += [f"| {knob} | {r['held_out']} | {r['chosen']} | {_fmt(r['train_change'])} | {_fmt(r['held_out_change'])} |"
                  for r in choice["folds"]]
    lines += ["", "| knob | decision |", "|---|---|"]
    lines += [f"| {knob} | {choice['chosen'] or 'default kept'} |" for knob, choice in knobs.items()]
    lines += ["", "## Depth agreement per variant (mean over N)", "",
              "| variant | " + " | ".join(c["capture"] for c in captures) + " |", "|---|" + "---|" * len(captures)]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(
            f"{np.mean([m['depth_agreement'] for m in c['variants'][name].values()]):.3f}" for c in captures) + " |")
    (out / "results.md").write_text("\n".join(lines) + "\n")

    fig, ax = plt.subplots(figsize=(10, 0.35 * len(names) + 1.5))
    height = 0.8 / len(groups)
    for i, g in enumerate(groups):
        ax.barh(np.arange(len(names)) + i * height, [deltas[g][n] for n in names], height, label=g)
    ax.set_yticks(np.arange(len(names)) + 0.4 - height / 2, names)
    ax.axvline(0, color="black", linewidth=0.8)
    ax.invert_yaxis()
    ax.set_xlabel("change of (all-pixel + covered PSNR) / 2 from the defaults, dB")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "objectives.png", dpi=110)
    plt.close(fig)


def _checked(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[list[Variant], tuple[int, ...], dict | None]:
    """The variants, the view counts and the saved results of --decide-from (None without it), each
    checked before any capture is read; a bad one exits 2 through ``parser.error``, naming its flag."""
    by_name = {v.name: v for v in VARIANTS}
    names = [] if args.variants is None else [n.strip() for n in args.variants.split(",") if n.strip()]
    if args.variants is not None and (unknown := [n for n in names if n not in by_name]):
        parser.error(f"--variants: unknown {', '.join(map(repr, unknown))}; expected names from: {', '.join(by_name)}")
    chosen = list(VARIANTS) if args.variants is None else [DEFAULT] + [by_name[n] for n in names if n != DEFAULT.name]
    if not (math.isfinite(args.scale) and 0 < args.scale <= 1):
        parser.error(f"--scale: expected a number in (0, 1], got {args.scale:g}")
    try:
        views = tuple(int(v) for v in args.views.split(","))
    except ValueError:
        parser.error(f"--views: expected comma-separated integers, got {args.views!r}")
    if not views or min(views) < 1:
        parser.error(f"--views: expected positive input counts, got {args.views!r}")
    saved = None
    if args.decide_from is not None:
        try:
            saved = json.loads(Path(args.decide_from).read_text())
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            parser.error(f"--decide-from: cannot read {args.decide_from} as JSON: {getattr(exc, 'strerror', None) or exc}")
        captures = saved.get("captures") if isinstance(saved, dict) else None
        if not (isinstance(captures, list) and captures and all(
                isinstance(c, dict) and "group" in c and isinstance(c.get("variants"), dict) and DEFAULT.name in c["variants"]
                for c in captures)):
            parser.error(f"--decide-from: {args.decide_from} holds no tuning results (a 'captures' list, each with "
                         f"its 'group' and its 'variants', '{DEFAULT.name}' among them)")
    try:  # before the runs, which would otherwise fail only when they write their results
        check_writable(args.out, "--out")
    except UnwritableFolder as exc:
        parser.error(str(exc))
    return chosen, views, saved


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m canonical_core.eval.tuning", description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="output folder (results.json, results.md, objectives.png)")
    parser.add_argument("--variants", default=None, help="comma-separated subset of: " + ", ".join(v.name for v in VARIANTS))
    parser.add_argument("--scale", type=float, default=1.0, help="image downscale factor in (0, 1] (default 1)")
    parser.add_argument("--views", default=",".join(map(str, VIEWS)), help="input counts N (each capture uses the prefix it allows)")
    parser.add_argument("--decide-from", metavar="RESULTS_JSON", default=None,
                        help="no runs: decide again from a saved results.json (with today's rule) and write the report")
    args = parser.parse_args(argv)
    chosen, views, saved = _checked(parser, args)
    if saved is not None:
        captures = saved["captures"]
        knobs = choose_per_knob(group_changes(captures), group_changes(captures, agreement))
        command = f"python -m canonical_core.eval.tuning --out {args.out} --decide-from {args.decide_from}"
        write_report({**saved, "group_changes": group_changes(captures), "knobs": knobs, "decided_by": command}, Path(args.out))
        print((Path(args.out) / "results.md").read_text())
        return 0
    try:
        steps = sum(len(chosen) * len(allowed_views(len(load_dataset(c.path)), views)) for c in CAPTURES)
    except ValueError as exc:  # a capture too short for the first input count
        parser.error(f"--views: {exc}")
    bar = tqdm(total=steps, file=sys.stderr, desc="tuning", unit="run", dynamic_ncols=True)
    captures = [score_capture(c, chosen, views, args.scale, bar) for c in CAPTURES]
    bar.close()
    knobs = choose_per_knob(group_changes(captures), group_changes(captures, agreement))
    joint = joint_variant(knobs, chosen)
    if joint is not None and sum(1 for c in knobs.values() if c["chosen"]) > 1:  # the chosen values together
        captures = [{**c, "variants": {**c["variants"], **score_capture(capture, [joint], views, args.scale)["variants"]}}
                    for c, capture in zip(captures, CAPTURES)]
    deltas = group_changes(captures)
    command = "python -m canonical_core.eval.tuning " + " ".join(argv if argv is not None else sys.argv[1:])
    results = {"command": command, "captures": captures, "group_changes": deltas, "knobs": knobs}
    write_report(results, Path(args.out))
    print((Path(args.out) / "results.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
