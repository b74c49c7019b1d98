"""Before and after: the speed and memory targets on this tree and on another checkout, in the same runs.

    python bench/ab.py --base ../before [--rounds 2] [--targets fold,long,memory,decode,render,service,solve]

``--base`` is another checkout of the project (a `git worktree` of an earlier commit, its compositor
built: ``python setup.py build_ext --inplace`` there). Every measurement runs in a child process
with one tree first on ``PYTHONPATH`` (and its own numba cache), the two trees alternating target
by target and round by round, so that the machine's drift falls on both. The measuring code is this
file's for both trees and uses only long-standing public calls (`Scene.fold`, `Scene.gaussians`,
`Scene.to_bytes`, `render`, Open3D through `eval.open3d_tsdf`), so both are timed doing the same
steps; the HTTP figures come from each tree's own ``bench/service.py``, whose table is read.

Per target, per tree: the median over the rounds of each figure (the rounds' values beside it) and
the load average at each run; then this tree over the base. Never asserts timings.

- ``fold``: ms a fold (median over the stream; the scene grows) and Open3D's TSDF integrate of the
  same frames at the same voxel size in the same process: the shelf's 50 frames at 4 mm, the office
  walk's first 100 at 1 cm. The scenes' digests are printed too: equal digests, equal results.
- ``long``: the office walk played twice at 1 cm (374 folds, after a warm-up fold in a throwaway
  scene): the median of the last 20 folds over the first 20, the slowest fold over the median, and
  after one decode `Scene.memory_bytes` per voxel and the process's resident growth per voxel.
- ``memory``: the office walk played twice at 1 cm by a scene keeping the undo records of its last
  folds (the tree's default depth, as a service session with a frame archive does, within half the map's bytes where the
  tree bounds them so), then one decode: bytes a voxel of its
  state (the map), its undo records, its caches (the decoded rows, the colour solve's views and
  solution) and all of them (`Scene.memory_bytes`), and the process's resident growth a voxel.
- ``decode``: the shelf's 50 frames at 4 mm (204k voxels): a decode from scratch (a scene restored
  from its snapshot bytes; median of 7), and a decode after each of the last 10 folds (median; the
  scene of the first 40 decoded once before them); where the tree has it, the latter also without
  F_scene (``gaussians(features=False)``, what a colour render decodes).
- ``render``: 170k Gaussians (``bench/render.py``'s scene) at 640x480 and 256x256, RGB, 2 threads,
  median of 5 after a warm-up render.
- ``service``: ``bench/service.py --frames 30 --renders 8 --solve-views 0`` of each tree: the
  in-process fold, the HTTP round trip and their ratio (medians).
- ``solve``: the shelf's 40 frames the protocol does not hold out, decoded after each fold by a scene
  keeping 16 colour-solve views and by one without: the extra ms a fold (mean, median, largest).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from common import machine_summary, print_table  # noqa: E402

DATA = HERE.parents[1] / "shared" / "data"
TARGETS = ("fold", "long", "memory", "decode", "render", "service", "solve")


def _ms(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return (time.perf_counter() - t0) * 1000.0


def _rss() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS"))


def measure_fold() -> dict:
    from canonical_core import SceneConfig
    from canonical_core.datasets import load_dataset
    from canonical_core.eval.open3d_tsdf import Open3DTSDF
    from canonical_core.scene import Scene

    out = {}
    for name, capture, voxel, n in (("shelf", "realsense_shelf", 0.004, 50), ("office", "hololens_office", 0.01, 100)):
        frames = list(load_dataset(DATA / capture, max_frames=n))
        warm = Scene(SceneConfig(voxel_size=voxel))
        for f in frames[:3]:
            warm.fold(f)
        scene = Scene(SceneConfig(voxel_size=voxel))
        fold = float(np.median([_ms(scene.fold, f) for f in frames]))
        tsdf = Open3DTSDF(voxel)
        open3d = float(np.median([_ms(tsdf.integrate, f) for f in frames]))
        out[f"{name} fold ms"], out[f"{name} Open3D ms"], out[f"{name} fold / Open3D"] = fold, open3d, fold / open3d
        out[f"{name} digest"] = scene.digest()[:16]
    return out


def _office_walked_twice(undo_depth: int, undo_share: float | None = None):
    """The office walk played twice at 1 cm (after a warm-up fold in a throwaway scene) by a scene
    keeping the undo records of its last ``undo_depth`` folds (within ``undo_share`` of the map's
    bytes, where the tree has that bound), then one decode: (the scene, each fold's ms, the resident
    memory before the scene was made)."""
    import inspect

    from canonical_core import SceneConfig
    from canonical_core.datasets import load_dataset
    from canonical_core.scene import Scene

    frames = list(load_dataset(DATA / "hololens_office"))
    warm = Scene(SceneConfig(voxel_size=0.01))
    warm.fold(frames[0])
    del warm
    gc.collect()
    before = _rss()
    scene = Scene(SceneConfig(voxel_size=0.01))
    if undo_share is not None and "max_share" in inspect.signature(scene.keep_undo).parameters:
        scene.keep_undo(undo_depth, undo_share)
    else:
        scene.keep_undo(undo_depth)
    ms = [_ms(scene.fold, f) for f in frames + frames]
    scene.gaussians()
    return scene, ms, before


def measure_long() -> dict:
    scene, ms, before = _office_walked_twice(0)
    median = float(np.median(ms))
    return {"folds": len(ms), "fold ms": median, "last 20 / first 20": float(np.median(ms[-20:]) / np.median(ms[:20])),
            "slowest / median": max(ms) / median, "memory_bytes a voxel": scene.memory_bytes() / len(scene),
            "resident growth a voxel": (_rss() - before) / len(scene)}


def _unsolved(config_class, voxel: float):
    """A config with the colour solve off (on by default since; a base tree from before the settings'
    groups has it off and no such group)."""
    try:
        return config_class(voxel_size=voxel, colour_solve={"views": 0})
    except ValueError:
        return config_class(voxel_size=voxel)


def measure_memory() -> dict:
    from canonical_core.scene.scene import DEFAULT_UNDO_DEPTH  # the records a session keeps, in each tree

    scene, _, before = _office_walked_twice(DEFAULT_UNDO_DEPTH, 0.5)
    n, all_in, undo = len(scene), scene.memory_bytes(), scene.undo_bytes()
    caches = scene._decoding.nbytes() + scene._keyframes.nbytes()  # both trees keep these parts so
    return {"voxels": n, "undo records": len(scene._undo), "state a voxel": (all_in - undo - caches) / n, "undo a voxel": undo / n,
            "caches a voxel": caches / n, "all in a voxel": all_in / n, "resident growth a voxel": (_rss() - before) / n}


def measure_decode() -> dict:
    import inspect

    from canonical_core import SceneConfig
    from canonical_core.datasets import load_dataset
    from canonical_core.scene import Scene

    frames = list(load_dataset(DATA / "realsense_shelf"))
    scene = Scene(_unsolved(SceneConfig, 0.004))  # the decode alone, as a render pays it
    for f in frames[:40]:
        scene.fold(f)
    snapshot = scene.to_bytes()
    whole = Scene.from_bytes(snapshot)
    for f in frames[40:]:
        whole.fold(f)
    whole_snapshot = whole.to_bytes()
    out = {"from scratch ms": float(np.median([_ms(Scene.from_bytes(whole_snapshot).gaussians) for _ in range(7)])),
           "voxels": len(whole)}
    kinds = {"after a fold ms": {}}
    if "features" in inspect.signature(scene.gaussians).parameters:
        kinds["after a fold, no F_scene, ms"] = {"features": False}
    for label, kwargs in kinds.items():
        s = Scene.from_bytes(snapshot)
        s.gaussians(**kwargs)
        times = []
        for f in frames[40:50]:
            s.fold(f)
            times.append(_ms(lambda: s.gaussians(**kwargs)))
        out[label] = float(np.median(times))
    return out


def measure_render() -> dict:
    from canonical_core.rendering import render

    from render import make_camera, make_scene  # bench/render.py's scene

    gaussians = make_scene(170_000)
    out = {}
    for width, height in ((640, 480), (256, 256)):
        camera = make_camera(width, height)

        def draw() -> None:
            render(gaussians, camera, ("rgb",), num_threads=2)

        draw()
        out[f"{width}x{height} ms"] = float(np.median([_ms(draw) for _ in range(5)]))
    return out


def measure_solve() -> dict:
    from canonical_core import SceneConfig
    from canonical_core.datasets import load_dataset
    from canonical_core.eval.protocol import interpolation_split
    from canonical_core.eval.run import default_voxel_size
    from canonical_core.scene import Scene

    sequence = load_dataset(DATA / "realsense_shelf")
    split = interpolation_split(len(sequence), (2, 4, 8, 16))
    voxel = default_voxel_size([sequence[p] for p in split.inputs[16]])
    try:
        solving = Scene(SceneConfig(voxel_size=voxel, colour_solve={"views": 16}))
    except ValueError:  # a base tree from before the settings' groups: the same setting, top level
        solving = Scene(SceneConfig(voxel_size=voxel, colour_solve_views=16))
    plain = Scene(_unsolved(SceneConfig, voxel))
    extra = []
    for p in range(len(sequence)):
        if p in split.heldout:
            continue
        solving.fold(sequence[p])
        plain.fold(sequence[p])
        extra.append(_ms(solving.decode) - _ms(plain.decode))
    return {"extra ms a fold, mean": float(np.mean(extra)), "median": float(np.median(extra)), "largest": max(extra)}


def measure_service(tree: Path) -> dict:
    """Each tree's own HTTP bench, its fold table read: medians of the in-process fold and the round trip."""
    text = subprocess.run([sys.executable, str(tree / "bench" / "service.py"), "--frames", "30", "--renders", "8",
                           "--solve-views", "0"], cwd=tree, env=_env(tree), capture_output=True, text=True,
                          check=True).stdout

    def median(label: str) -> float:
        return float(re.search(rf"\|\s*{re.escape(label)}\s*\|\s*([\d.]+)", text).group(1))

    fold, trip = median("in-process Scene.fold"), median("HTTP round trip (client)")
    return {"in-process fold ms": fold, "round trip ms": trip, "round trip / fold": trip / fold}


MEASURES = {"fold": measure_fold, "long": measure_long, "memory": measure_memory, "decode": measure_decode,
            "render": measure_render, "solve": measure_solve}


def _env(tree: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(tree / ".numba_cache")}


def run_child(target: str, tree: Path) -> dict:
    """One measurement of ``target`` with ``tree``'s code, in a fresh process; with the load average."""
    load = os.getloadavg()[0]
    if target == "service":
        figures = measure_service(tree)
    else:
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--measure", target], cwd=tree,
                              env=_env(tree), capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"{target} on {tree} failed:\n{done.stderr[-3000:]}")
        figures = json.loads(done.stdout.strip().splitlines()[-1])
    return {**figures, "load": load}


def _number(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def _cell(values: list) -> str:
    if isinstance(values[0], str):
        return " / ".join(dict.fromkeys(values))
    return f"{_number(float(np.median(values)))} ({', '.join(_number(v) for v in values)})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, help="the other checkout (the 'before')")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated subset of {','.join(TARGETS)}")
    parser.add_argument("--measure", choices=sorted(MEASURES), help=argparse.SUPPRESS)  # the child's entry point
    args = parser.parse_args()
    if args.measure:
        print(json.dumps(MEASURES[args.measure]()))
        return
    if args.base is None:
        parser.error("--base: give the checkout to compare against")
    targets = args.targets.split(",")
    if unknown := set(targets) - set(TARGETS):
        parser.error(f"--targets: unknown {sorted(unknown)}; expected some of {list(TARGETS)}")
    trees = {"base": args.base.resolve(), "this tree": HERE.parent}
    print(machine_summary())
    print(f"base: {trees['base']}\nthis tree: {trees['this tree']}\nrounds: {args.rounds}, trees alternating\n")
    results = {(t, name): [] for t in targets for name in trees}
    for _ in range(args.rounds):
        for target in targets:
            for name, tree in trees.items():
                results[(target, name)].append(figures := run_child(target, tree))
                print(f"  {target} on {name} done (load {figures['load']:.2f})", file=sys.stderr, flush=True)
    for target in targets:
        base, this = results[(target, "base")], results[(target, "this tree")]
        rows = []
        for key in this[0]:
            if key not in base[0]:
                rows.append({"figure": key, "base": "-", "this tree": _cell([r[key] for r in this]), "this / base": "-"})
                continue
            b, t = [r[key] for r in base], [r[key] for r in this]
            ratio = "-" if isinstance(b[0], str) or not np.median(b) else f"{np.median(t) / np.median(b):.2f}"
            rows.append({"figure": key, "base": _cell(b), "this tree": _cell(t), "this / base": ratio})
        print_table(f"{target}: medians over the rounds (each round's value in brackets)", rows)


if __name__ == "__main__":
    main()
