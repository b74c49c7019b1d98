"""Colour-solve benchmark: the render-consistent colour solve's cost and what it buys.

    python bench/colour_solve.py [--data ../shared/data/realsense_shelf] [--views 4,8,16] [--scales 1,0.5] [--repeats 3]
    python bench/colour_solve.py --stream [--refresh 1,4,8,16] [--kept 16]
    python bench/colour_solve.py --pause [--frames 20] [--rounds 3] [--solve-nice 19]
    python bench/colour_solve.py --costs [--frames 20]

For N input views of the evaluation protocol (640x480, its voxel size), kept at each keyframe
scale (`SceneConfig.colour_solve.scale`; 0.5 is the default): ms for one kept view's part of the
solve's system (`weight_rows_and_blend`: its rows of compositing weights and its render, one pass
of the C compositor; the PyTorch reference on the first view once, for the ratio), ms
for the whole solve (weights of every view, the sparse system, the library's default CG iterations), ms for a
streaming scene's re-solve of the same system from its solution (`REFRESH_ITERATIONS` steps), its
nonzeros, and held-out all-pixel / covered PSNR before and after. Prints medians / min / max and the
machine. Never asserts timings.

``--stream`` measures a streaming session instead: every frame of the capture that the protocol
does not hold out is folded in order, and the scene decoded after each fold, as a viewer does, by a
scene that solves colours (``--kept`` views, `SceneConfig.colour_solve.refresh` each of
``--refresh``) and by one that does not. Per refresh: the solves made, the decode's extra ms per
fold (mean: the solve's cost amortised over the stream; median; largest), and held-out all-pixel /
covered PSNR of the last decode, against the same scene solved from scratch over the same kept views.

``--pause`` measures the service's background solve: the real service (`canonical serve`, its
``solve_nice`` from ``--solve-nice``) on a free port, ``--frames`` frames of the capture (640x480,
voxel 0.004 m, every other frame) posted one after the other as a streaming client does, to a
session with the defaults and one with the solve off (``colour_solve.views`` 0) in turn, then a
pause. Per round: the two sessions' frame round trips (median), what the fold path pays for keeping
views and solving; from the last frame's acknowledgement, ms until the session's stats say its
colours are solved for every frame (``colours_solved_frames``), and until a render that shows them
has come back; and the solves run in the pause.

``--costs`` measures what keeping the views costs the fold path, in one process: a scene with the
solve off and one with the defaults fold the same ``--frames`` frames (640x480, voxel 0.004 m) in
turn; per scene, the fold's ms per frame and the ms of a render's decode after each fold
(`Scene.gaussians` with ``colours="last"``, as the service decodes: no solve; the scene with the
solve solves once, untimed, halfway, so that its later decodes apply a solution), medians / min /
max, and the bytes the scene holds at the end.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import machine_summary, print_table, stats_ms, time_each  # noqa: E402

import numpy as np  # noqa: E402

from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.decode import colour_system, solve_colours  # noqa: E402
from canonical_core.eval.methods import SplatModel, build  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.eval.run import default_voxel_size, score  # noqa: E402
from canonical_core.frame import resize_frame  # noqa: E402
from canonical_core.decode.colour_solve import COVERED_ALPHA, ROW_MIN_WEIGHT  # noqa: E402
from canonical_core.decode import colour_offsets, with_colour_offsets  # noqa: E402
from canonical_core.rendering.weights import weight_rows_and_blend  # noqa: E402
from canonical_core.scene import Scene, SceneConfig  # noqa: E402
from canonical_core.scene.decoding import REFRESH_ITERATIONS  # noqa: E402
from client.cli.capture import frame_arrays  # noqa: E402
from client.cli.launch import free_port, start_service  # noqa: E402
from client.sdk import Client  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def stream(sequence, split, voxel: float, refreshes: list[int], kept: int) -> None:
    """The ``--stream`` table (module docstring)."""
    targets = [sequence[p] for p in split.heldout]
    frames = [sequence[p] for p in range(len(sequence)) if p not in split.heldout]
    rows = []
    for refresh in refreshes:
        solving = Scene(SceneConfig(voxel_size=voxel, colour_solve={"views": kept, "refresh": refresh}))
        plain = Scene(SceneConfig(voxel_size=voxel, colour_solve={"views": 0}))
        extra, solves = [], 0
        for frame in frames:
            solving.fold(frame)
            plain.fold(frame)
            before = solving._decoding.solution
            (with_solve,), (without,) = time_each(lambda _: solving.decode(), [0]), time_each(lambda _: plain.decode(), [0])
            extra.append(with_solve - without)
            solves += solving._decoding.solution is not before
        base = plain.decode()
        full = with_colour_offsets(base, colour_offsets(base, solving._keyframes.frames()))
        streamed = score(SplatModel(solving.decode()), targets, voxel).metrics
        scratch = score(SplatModel(full), targets, voxel).metrics
        fused = score(SplatModel(base), targets, voxel).metrics
        rows.append({
            "refresh": refresh, "solves": solves, "extra ms / fold: mean": f"{np.mean(extra):.0f}",
            "median": f"{np.median(extra):.0f}", "max": f"{max(extra):.0f}",
            "held-out dB, streamed": f"{streamed['psnr']:.2f} / {streamed['psnr_covered']:.2f}",
            "solved from scratch": f"{scratch['psnr']:.2f} / {scratch['psnr_covered']:.2f}",
            "fused colours": f"{fused['psnr']:.2f} / {fused['psnr_covered']:.2f}",
        })  # fmt: skip
        print(f"refresh {refresh} done", file=sys.stderr, flush=True)
    print_table(f"Streaming colour solve: {len(frames)} frames folded, decoded after each, {kept} kept views at "
                f"{SceneConfig(voxel_size=voxel).colour_solve.scale:g}, voxel {voxel:.4f} m", rows)


def solves_done(client: Client) -> int:
    text = client._request("GET", "/metrics").text
    return int(float(next(line.split()[1] for line in text.splitlines()
                          if line.startswith("canonical_colour_solves_done_total "))))


def pause(sequence, frames: int, rounds: int, solve_nice: int) -> None:
    """The ``--pause`` table (module docstring)."""
    os.environ["CANONICAL_SOLVE_NICE"] = str(solve_nice)  # the service's setting, from its environment
    payloads = [frame_arrays(sequence[i]) for i in range(0, 2 * frames, 2)]
    view = payloads[len(payloads) // 2]
    K, c2w, (h, w) = view["K"], view["c2w"], view["rgb"].shape[:2]
    rows = []
    with tempfile.TemporaryDirectory() as data_dir:
        port = free_port()
        service = start_service(port, Path(data_dir))
        try:
            with Client(f"http://127.0.0.1:{port}", timeout=600) as client:
                for r in range(rounds):
                    sessions = {"off": client.create_session(voxel_size=0.004, colour_solve={"views": 0}),
                                "on": client.create_session(voxel_size=0.004)}
                    trips = {name: [] for name in sessions}
                    for p in payloads:  # in turn, so that both sessions' frames meet the same background solves
                        for name, session in sessions.items():
                            trips[name] += time_each(lambda q: session.add_frame(**q), [p])
                    acked = time.perf_counter()
                    before = solves_done(client)
                    while session.stats()["colours_solved_frames"] != frames:  # the "on" session
                        time.sleep(0.02)
                    solved = time.perf_counter()
                    session.render(K, c2w, w, h)
                    shown = time.perf_counter()
                    rows.append({
                        "round": r + 1, "frame round trip ms, solve off / on": f"{np.median(trips['off']):.0f} / "
                                                                            f"{np.median(trips['on']):.0f}",
                        "last ack -> solved ms": f"{(solved - acked) * 1000:.0f}",
                        "last ack -> solved render ms": f"{(shown - acked) * 1000:.0f}",
                        "solves in the pause": solves_done(client) - before,
                    })  # fmt: skip
                    print(f"round {r + 1} done", file=sys.stderr, flush=True)
        finally:
            service.terminate()
            service.wait(60)
    print_table(f"Background colour solve, real service (solve_nice {solve_nice}): {frames} frames at 640x480, "
                f"voxel 0.004 m, then a pause", rows)


def costs(sequence, frames: int) -> None:
    """The ``--costs`` table (module docstring)."""
    scenes = {"off": Scene(SceneConfig(voxel_size=0.004, colour_solve={"views": 0})),
              "on (defaults)": Scene(SceneConfig(voxel_size=0.004))}
    fold_ms, decode_ms = {k: [] for k in scenes}, {k: [] for k in scenes}
    for i in range(frames):
        frame = sequence[i]
        for name, scene in scenes.items():  # in turn, so that the load falls on both alike
            fold_ms[name] += time_each(scene.fold, [frame])
            decode_ms[name] += time_each(lambda _: scene.gaussians(colours="last", features=False), [0])
        if i == frames // 2:  # untimed: from here on its decodes apply a solution, as the service's do
            scenes["on (defaults)"].solve_colours()
    rows = [{"colour solve": name, "fold ms": stats_ms(fold_ms[name]), "render decode ms": stats_ms(decode_ms[name]),
             "memory MB": f"{scene.memory_bytes() / 1e6:.1f}", "kept views MB": f"{scene._keyframes.nbytes() / 1e6:.2f}"}
            for name, scene in scenes.items()]
    print_table(f"Keeping the views: {frames} frames at 640x480, voxel 0.004 m (median / min / max)", rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument("--views", default="4,8,16", help="input view counts of the protocol (2, 4, 8, 16)")
    parser.add_argument("--scales", default="1,0.5", help="keyframe scales, each in (0, 1]")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--stream", action="store_true", help="a streaming session decoded after every fold")
    parser.add_argument("--refresh", default="1,4,8,16", help="with --stream: colour_solve.refresh values")
    parser.add_argument("--kept", type=int, default=16, help="with --stream: colour_solve.views")
    parser.add_argument("--pause", action="store_true", help="the service's background solve after a stream pauses")
    parser.add_argument("--costs", action="store_true", help="the fold and a render's decode with the solve off and on")
    parser.add_argument("--frames", type=int, default=20, help="with --pause or --costs: frames streamed")
    parser.add_argument("--rounds", type=int, default=3, help="with --pause: rounds")
    parser.add_argument("--solve-nice", type=int, default=19, help="with --pause: the service's solve_nice")
    args = parser.parse_args()
    views = [int(v) for v in args.views.split(",")]
    scales = [float(s) for s in args.scales.split(",")]
    if any(v not in (2, 4, 8, 16) for v in views) or args.repeats < 1 or not all(0 < s <= 1 for s in scales):
        parser.error("--views: a list from 2,4,8,16; --scales: numbers in (0, 1]; --repeats: at least 1")
    sequence = load_dataset(args.data)
    if args.pause or args.costs:
        print(machine_summary())
        return pause(sequence, args.frames, args.rounds, args.solve_nice) if args.pause else costs(sequence, args.frames)
    split = interpolation_split(len(sequence), (2, 4, 8, 16))
    targets = [sequence[p] for p in split.heldout]
    voxel = default_voxel_size([sequence[p] for p in split.inputs[16]])
    print(machine_summary())
    if args.stream:
        return stream(sequence, split, voxel, [int(r) for r in args.refresh.split(",")], args.kept)
    rows = []
    for n in views:
        full_size = [sequence[p] for p in split.inputs[n]]
        model, _ = build("canonical:colour_solve.views=0", full_size, voxel)  # the fused colours
        splats = model.splats
        before = score(model, targets, voxel).metrics
        for scale in scales:
            inputs = [resize_frame(f, scale) for f in full_size]
            def view_part(f, backend="cpu"):  # a view's part of the system, as the solve makes it
                return weight_rows_and_blend(splats, f.camera, COVERED_ALPHA, backend, min_weight=ROW_MIN_WEIGHT)

            weights_ms = time_each(view_part, inputs * args.repeats)
            reference_ms = time_each(lambda f: view_part(f, "reference"), inputs[:1])
            solve_ms = time_each(lambda _: solve_colours(splats, inputs), range(args.repeats))
            solution = colour_offsets(splats, inputs)
            resolve_ms = time_each(lambda _: colour_offsets(splats, inputs, solution, iterations=REFRESH_ITERATIONS),
                                   range(args.repeats))
            nonzeros = colour_system(splats, inputs)[0].values().numel()
            after = score(SplatModel(with_colour_offsets(splats, solution)), targets, voxel).metrics
            rows.append({
                "N": n, "kept at": f"{inputs[0].width}x{inputs[0].height}", "Gaussians": len(splats),
                "nonzeros (M)": f"{nonzeros / 1e6:.1f}", "rows + blend ms/view": stats_ms(weights_ms),
                "reference / fast": f"{reference_ms[0] / float(np.median(weights_ms)):.0f}x", "solve ms": stats_ms(solve_ms),
                "re-solve ms": stats_ms(resolve_ms),
                "held-out before dB": f"{before['psnr']:.2f} / {before['psnr_covered']:.2f}",
                "after dB": f"{after['psnr']:.2f} / {after['psnr_covered']:.2f}",
            })  # fmt: skip
            print(f"N={n} at {scale:g} done", file=sys.stderr, flush=True)
    print_table(f"Colour solve, {Path(args.data).name}, 640x480, voxel {voxel:.4f} m (median / min / max)", rows)


if __name__ == "__main__":
    main()
