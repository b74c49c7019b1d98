"""Rasterizer benchmark: ms per frame of render() for the cpu and reference backends, and gsplat on CUDA.

Usage: NUMBA_CACHE_DIR=.numba_cache python bench/render.py [--quick]

Prints a table; asserts nothing. The scene is synthetic but shaped like a decoded capture:
Gaussians on a back wall, a floor and two boxes 2-4 m in front of the camera, flattened along
the surface normal, standard deviation 0.7-3 px at 640x480 (boxes of 5-19 px across their 3 sigma),
opacity 0.3-1, degree-1 SH colour, in random order. Rows "shelf" render the real scene decoded from
all of ../shared/data/realsense_shelf (when it is there). Rows "gsplat" appear where CUDA and
gsplat are installed: the same scenes moved to the GPU, timed to the end of the GPU's work. Timings are
wall-clock medians after warm-up on a machine that may be shared: read them with the load
average printed at the top.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, time_each  # noqa: E402

from canonical_core.camera import Camera  # noqa: E402
from canonical_core.datasets import load_tsdf_fusion  # noqa: E402
from canonical_core.gaussians import Gaussians, rgb_to_sh_dc  # noqa: E402
from canonical_core.rendering import render  # noqa: E402
from canonical_core.rendering.cpu_tiles import compositor_build  # noqa: E402
from canonical_core.rendering.gsplat_backend import gsplat_available  # noqa: E402
from canonical_core.scene import Scene, SceneConfig  # noqa: E402

FOCAL_AT_640 = 525.0
SHELF = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_shelf"


def make_camera(width: int, height: int) -> Camera:
    f = FOCAL_AT_640 * width / 640
    K = [[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]
    return Camera(K=K, c2w=np.eye(4), width=width, height=height)


def make_scene(n: int, feature_dim: int = 0, seed: int = 0) -> Gaussians:
    """n Gaussians on surfaces in front of an identity camera (z forward, y down)."""
    rng = np.random.default_rng(seed)
    surface = rng.choice(4, size=n, p=[0.45, 0.25, 0.15, 0.15])
    a, b = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    means = np.empty((n, 3))
    normals = np.empty((n, 3))
    wall = surface == 0  # back wall at z = 4
    means[wall] = np.stack([2.2 * a[wall], 1.6 * b[wall], np.full(wall.sum(), 4.0)], 1)
    normals[wall] = [0, 0, 1]
    floor = surface == 1  # floor 1 m below the camera
    means[floor] = np.stack([2.2 * a[floor], np.full(floor.sum(), 1.0), 2.5 + 1.5 * b[floor]], 1)
    normals[floor] = [0, 1, 0]
    for k, (cx, cy, cz, s) in zip((2, 3), ((-0.6, 0.4, 2.0, 0.5), (0.7, 0.2, 2.8, 0.7))):
        box = surface == k  # front faces of two boxes
        means[box] = np.stack([cx + s * a[box], cy + s * b[box], np.full(box.sum(), cz)], 1)
        normals[box] = [0, 0, 1]
    depth = means[:, 2]
    pixel_sigma = rng.uniform(0.7, 3.0, n)  # standard deviation in pixels at 640x480
    tangent_scale = pixel_sigma * depth / FOCAL_AT_640
    scales = np.stack([tangent_scale, tangent_scale * rng.uniform(0.5, 1.0, n), tangent_scale * 0.1], 1)
    # Rotate local z onto the surface normal, then spin about it.
    quats = np.zeros((n, 4))
    spin = rng.uniform(0, np.pi, n)
    quats[:, 0] = np.cos(spin / 2)
    quats[:, 3] = np.sin(spin / 2)
    up = normals[:, 1] == 1  # floor: local z -> world y is a 90 degree turn about x
    turn = np.array([np.cos(-np.pi / 4), np.sin(-np.pi / 4), 0, 0])
    quats[up] = quat_multiply(np.broadcast_to(turn, (up.sum(), 4)), quats[up])
    sh = np.zeros((n, 4, 3))
    sh[:, 0] = rgb_to_sh_dc(rng.uniform(0.1, 0.9, (n, 3)))
    sh[:, 1:] = rng.normal(0, 0.1, (n, 3, 3))
    t = lambda x: torch.as_tensor(x, dtype=torch.float32)  # noqa: E731
    return Gaussians(
        means=t(means), scales=t(scales), quats=t(quats), opacities=t(rng.uniform(0.3, 1.0, n)), sh=t(sh),
        features=t(rng.normal(0, 1, (n, feature_dim))) if feature_dim else None,
    )  # fmt: skip


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # [N, 4] wxyz
    w1, x1, y1, z1 = p.T
    w2, x2, y2, z2 = q.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], 1)  # fmt: skip


RESOLUTIONS = ((256, 256), (640, 480))
SIZES = (10_000, 50_000, 170_000)
FEATURE_DIM = 32
TARGETS_MS = {(170_000, (256, 256), "rgb"): 25, (170_000, (640, 480), "rgb"): 60}  # the speed targets, 2 threads
OUTPUTS = {"rgb": ("rgb", "depth", "alpha"), "rgb+32f": ("rgb", "depth", "alpha", "features")}


def shelf_cases() -> list[tuple[str, Gaussians, Camera]]:
    """The decoded shelf scene (all frames folded at 4 mm) at an input frame's pose, 640x480 and a
    256x256 centre crop at the same focal length scaled to 256 rows; [] without ../shared/data."""
    if not SHELF.is_dir():
        return []
    frames = load_tsdf_fusion(SHELF)
    scene = Scene(SceneConfig(voxel_size=0.004))
    for frame in frames:
        scene.fold(frame)
    gaussians, camera = scene.decode(), frames[len(frames) // 2].camera
    print(f"shelf: {len(frames)} frames folded at 4 mm, {len(gaussians)} Gaussians, rendered at frame {len(frames) // 2}")
    scale = 256 / camera.height
    K = [[camera.fx * scale, 0, 127.5], [0, camera.fy * scale, 127.5], [0, 0, 1]]
    small = Camera(K=K, c2w=camera.c2w64(), width=256, height=256)
    return [("shelf", gaussians, small), ("shelf", gaussians, camera)]


def machine() -> str:
    return machine_summary() + f"numba threading layer: {numba.threading_layer()}, compositor build: {compositor_build}"


def time_render(gaussians: Gaussians, camera: Camera, outputs, backend: str, threads: int, repeats: int) -> list[float]:
    """Milliseconds per render, after a warm-up render. On the GPU the clock stops when its work ends."""
    if backend == "gsplat":
        gaussians = gaussians.to("cuda")

    def draw(_) -> None:
        render(gaussians, camera, outputs, backend=backend, num_threads=threads)
        if backend == "gsplat":
            torch.cuda.synchronize()

    draw(None)
    return time_each(draw, range(repeats))


# Run in a fresh interpreter: seconds to import, seconds of the first render (numba cache warm),
# then the resident memory a second render adds at its peak (VmHWM after resetting it to VmRSS).
FRESH_PROCESS = """
import sys, time
from pathlib import Path
start = time.perf_counter()
import torch
from canonical_core.rendering import render
imported = time.perf_counter()
scene, camera, outputs = torch.load(sys.argv[1], weights_only=False)
first = time.perf_counter()
render(scene, camera, outputs, num_threads=int(sys.argv[2]))
rendered = time.perf_counter()
def status(field):
    return next(int(l.split()[1]) * 1024 for l in Path("/proc/self/status").read_text().splitlines() if l.startswith(field))
Path("/proc/self/clear_refs").write_text("5")
before = status("VmRSS:")
render(scene, camera, outputs, num_threads=int(sys.argv[2]))
print(imported - start, rendered - first, status("VmHWM:") - before)
"""


def fresh_process(scene: Gaussians, camera: Camera, outputs, threads: int, path: Path, env: dict) -> list[float]:
    torch.save((scene, camera, outputs), path)
    command = [sys.executable, "-c", FRESH_PROCESS, str(path), str(threads)]
    return [float(x) for x in subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout.split()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="170k Gaussians only, fewer repeats")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    sizes = SIZES[-1:] if args.quick else SIZES
    repeats = 3 if args.quick else args.repeats
    threads = sorted({1, min(2, os.cpu_count() or 1)})
    render(Gaussians.empty(), make_camera(16, 16))  # starts numba's thread pool, which machine() names
    print(machine())
    gpu = torch.cuda.is_available() and gsplat_available()
    if gpu:
        print(f"gsplat on {torch.cuda.get_device_name()}")
    scenes = {n: make_scene(n, FEATURE_DIM) for n in sizes}
    cases = [(n, scenes[n], make_camera(width, height)) for n in sizes for width, height in RESOLUTIONS]
    cases += shelf_cases()
    print(f"\nms per frame: median / min / max of {repeats} after a warm-up render (targets apply to 2 threads)\n")
    header = f"{'backend':<10}{'gaussians':>10}{'image':>10}{'channels':>10}{'threads':>8}{'median':>9}{'min':>8}{'max':>8}"
    print(header + "  target")
    for n, gaussians, camera in cases:
        width, height = camera.width, camera.height
        for channels, outputs in OUTPUTS.items():
            if "features" in outputs and gaussians.features.shape[1] != FEATURE_DIM:
                channels = f"rgb+{gaussians.features.shape[1]}f"
            runs = [("cpu", t) for t in threads]
            if n == SIZES[0] and width == 256:  # the reference is O(splats x pixels): small cases only
                runs.append(("reference", threads[-1]))
            if gpu:
                runs.append(("gsplat", threads[-1]))
            for backend, t in runs:
                torch.set_num_threads(t)
                times = time_render(gaussians, camera, outputs, backend, t, 3 if backend == "reference" else repeats)
                target = TARGETS_MS.get((n, (width, height), channels)) if backend == "cpu" and t == 2 else None
                print(f"{backend:<10}{n:>10}{f'{width}x{height}':>10}{channels:>10}{t:>8}{statistics.median(times):>9.1f}"
                      f"{min(times):>8.1f}{max(times):>8.1f}  {f'<= {target} ms' if target else ''}")  # fmt: skip

    print(f"\nfresh process, cpu backend, {threads[-1]} threads: seconds to import and to render once (numba cache warm),")
    print("and the peak resident memory one more render adds (glibc told to unmap freed blocks, so it shows).")
    print("The target is on the first render() call; import is mostly `import torch`, and the call includes")
    print("numba's one-time start-up in a process (~0.5 s, paid by the first call of any numba function)\n")
    print(f"{'gaussians':>10}{'image':>10}{'channels':>10}{'import s':>10}{'render s':>10}{'sum s':>8}{'peak MB':>9}  target")
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
    with tempfile.TemporaryDirectory() as workdir:
        for n in sizes:
            for width, height in RESOLUTIONS:
                for channels, outputs in OUTPUTS.items():
                    camera = make_camera(width, height)
                    path = Path(workdir) / "scene.pt"
                    imported, first, peak = fresh_process(scenes[n], camera, outputs, threads[-1], path, env)
                    note = "render <= 1.5 s" if (n, width, channels) == (SIZES[-1], 256, "rgb") else ""
                    print(f"{n:>10}{f'{width}x{height}':>10}{channels:>10}{imported:>10.2f}{first:>10.2f}"
                          f"{imported + first:>8.2f}{peak / 2**20:>9.0f}  {note}")  # fmt: skip


if __name__ == "__main__":
    main()
