"""Mesh export against Open3D's TSDF mesh: Chamfer distance to held-out depth, extraction time, pictures.

    python bench/mesh.py [--out docs/mesh] [--repeats 3] [--datasets realsense_shelf:0.004:3 sun3d_studyroom:0.01:4]
                         [--min-support 0 1]

Each dataset is NAME:VOXEL:DEPTH_MAX (metres). Its frames are split by the evaluation protocol
(`canonical_core.eval.protocol.interpolation_split`): the 10 held-out frames are never fused; every
other frame is folded into our scene and integrated into Open3D's VoxelBlockGrid TSDF
(`canonical_core.eval.open3d_tsdf.Open3DTSDF`: block resolution 16, truncation 8 voxels) at the same
voxel size, both with depth cut at DEPTH_MAX. Then both meshes are extracted: ours by
`canonical_core.scene.mesh.surface_mesh` (the route's own function; default settings, and once more
per further ``--min-support`` value, R_scene a voxel needs to count), Open3D's by
``VoxelBlockGrid.extract_triangle_mesh`` (its default weight threshold 3). Extraction is timed as the
median of ``--repeats`` runs (the first run of ours also compiles or loads its numba kernels, so one
untimed run goes first).

Distances (metres), against the held-out frames' sensor depth lifted to world points (every 2nd
pixel of each axis, depth in (0, DEPTH_MAX]); each mesh is sampled uniformly by area (a point per
(voxel / 2)^2 of surface, at most 3 million):
- completeness: from each held-out point to the nearest mesh sample (what the mesh misses);
- accuracy: from each mesh sample that a held-out camera sees to the nearest held-out point (what
  the mesh invents). "Sees": it projects onto a pixel with depth and lies at most 5 cm behind it,
  so surface the held-out views never saw is not counted against either mesh;
- Chamfer: the mean of the two means (symmetric). Medians are printed too: the held-out depth has
  its own flying pixels and holes, which the means feel.

Writes ``OUT/<dataset>.png`` (ours left, Open3D right; vertex colour above, shaded by the face
normal below; seen from the middle held-out camera, pulled back) and prints the tables with the
machine. Never asserts timings.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numba
import numpy as np
from PIL import Image, ImageDraw
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine_summary, print_table  # noqa: E402

from canonical_core import Camera, SceneConfig  # noqa: E402
from canonical_core.datasets import load_dataset  # noqa: E402
from canonical_core.eval.open3d_tsdf import Open3DTSDF  # noqa: E402
from canonical_core.eval.protocol import interpolation_split  # noqa: E402
from canonical_core.scene import Scene  # noqa: E402
from canonical_core.scene.mesh import surface_mesh  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEEN_BEHIND = 0.05  # metres a mesh sample may lie behind a held-out pixel's depth and still count as seen
MAX_SAMPLES = 3_000_000


def lifted(frame, depth_max: float, step: int = 2) -> np.ndarray:  # [N, 3] world points of a frame's depth
    depth = frame.depth.numpy()[::step, ::step]
    v, u = np.nonzero((depth > 0) & (depth <= depth_max))
    z = depth[v, u].astype(np.float64)
    K, c2w = frame.camera.K64(), frame.camera.c2w64()
    cam = np.stack([(u * step - K[0, 2]) / K[0, 0] * z, (v * step - K[1, 2]) / K[1, 1] * z, z], 1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def sample_surface(vertices: np.ndarray, faces: np.ndarray, spacing: float, rng) -> np.ndarray:  # [M, 3]
    """Points uniform by area on the triangles, about one per ``spacing``^2."""
    a, b, c = (vertices[faces[:, i]].astype(np.float64) for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    count = int(min(MAX_SAMPLES, max(1, area.sum() / spacing**2)))
    tri = rng.choice(len(faces), count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count))[:, None], rng.random(count)[:, None]
    return (1 - r1) * a[tri] + r1 * (1 - r2) * b[tri] + r1 * r2 * c[tri]


def seen_by(points: np.ndarray, frames, depth_max: float) -> np.ndarray:  # [M] bool
    """Points some held-out camera sees: on one of its pixels with depth, at most SEEN_BEHIND behind it."""
    seen = np.zeros(len(points), bool)
    for f in frames:
        K, w2c = f.camera.K64(), np.linalg.inv(f.camera.c2w64())
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        front = z > 1e-3
        u = np.full(len(points), -1, np.int64)
        v = np.full(len(points), -1, np.int64)
        u[front] = np.floor(K[0, 0] * cam[front, 0] / z[front] + K[0, 2] + 0.5).astype(np.int64)
        v[front] = np.floor(K[1, 1] * cam[front, 1] / z[front] + K[1, 2] + 0.5).astype(np.int64)
        inside = front & (u >= 0) & (v >= 0) & (u < f.camera.width) & (v < f.camera.height)
        depth = np.zeros(len(points))
        depth[inside] = f.depth.numpy()[v[inside], u[inside]]
        seen |= inside & (depth > 0) & (depth <= depth_max) & (z <= depth + SEEN_BEHIND)
    return seen


def distances(vertices, faces, heldout_points, heldout_frames, voxel, depth_max, rng) -> dict:
    samples = sample_surface(vertices, faces, voxel / 2, rng)
    completeness = cKDTree(samples).query(heldout_points, workers=-1)[0]
    visible = samples[seen_by(samples, heldout_frames, depth_max)]
    accuracy = cKDTree(heldout_points).query(visible, workers=-1)[0]
    return {"accuracy mean / median mm": f"{accuracy.mean() * 1000:.1f} / {np.median(accuracy) * 1000:.1f}",
            "completeness mean / median mm": f"{completeness.mean() * 1000:.1f} / {np.median(completeness) * 1000:.1f}",
            "Chamfer mm": f"{(accuracy.mean() + completeness.mean()) / 2 * 1000:.1f}",
            "held-out points within 2 voxels": f"{(completeness < 2 * voxel).mean() * 100:.1f} %"}


def timed(fn, repeats: int) -> tuple[object, float]:
    """fn's result and the median seconds of ``repeats`` runs."""
    seconds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        seconds.append(time.perf_counter() - t0)
    return result, float(np.median(seconds))


@numba.njit(cache=True)
def _rasterise(uv, z, faces, zbuf, face_of, bary):
    """Z-buffer the projected triangles (both windings): nearest face per pixel and its barycentrics."""
    h, w = zbuf.shape
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if z[a] <= 0 or z[b] <= 0 or z[c] <= 0:
            continue
        area = (uv[b, 0] - uv[a, 0]) * (uv[c, 1] - uv[a, 1]) - (uv[b, 1] - uv[a, 1]) * (uv[c, 0] - uv[a, 0])
        if area == 0:
            continue
        x0 = max(int(np.floor(min(uv[a, 0], uv[b, 0], uv[c, 0]))), 0)
        x1 = min(int(np.ceil(max(uv[a, 0], uv[b, 0], uv[c, 0]))), w - 1)
        y0 = max(int(np.floor(min(uv[a, 1], uv[b, 1], uv[c, 1]))), 0)
        y1 = min(int(np.ceil(max(uv[a, 1], uv[b, 1], uv[c, 1]))), h - 1)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                l0 = ((uv[b, 0] - x) * (uv[c, 1] - y) - (uv[b, 1] - y) * (uv[c, 0] - x)) / area
                l1 = ((uv[c, 0] - x) * (uv[a, 1] - y) - (uv[c, 1] - y) * (uv[a, 0] - x)) / area
                l2 = 1.0 - l0 - l1
                if l0 < 0 or l1 < 0 or l2 < 0:
                    continue
                depth = l0 * z[a] + l1 * z[b] + l2 * z[c]
                if depth < zbuf[y, x]:
                    zbuf[y, x], face_of[y, x] = depth, f
                    bary[y, x, 0], bary[y, x, 1], bary[y, x, 2] = l0, l1, l2


def picture(vertices, faces, colours, camera: Camera) -> tuple[np.ndarray, np.ndarray]:  # colour, shaded [H, W, 3] uint8
    """The mesh seen by ``camera``: vertex colours, and grey shaded by each face's normal (headlight)."""
    K, w2c = camera.K64(), np.linalg.inv(camera.c2w64())
    cam = vertices.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uv = np.stack([K[0, 0] * cam[:, 0] / np.where(z > 0, z, 1) + K[0, 2], K[1, 1] * cam[:, 1] / np.where(z > 0, z, 1) + K[1, 2]], 1)
    h, w = camera.height, camera.width
    zbuf, face_of, bary = np.full((h, w), np.inf), np.full((h, w), -1, np.int64), np.zeros((h, w, 3))
    _rasterise(uv, z, faces.astype(np.int64), zbuf, face_of, bary)
    hit = face_of >= 0
    f = faces[face_of[hit]]
    rgb = np.full((h, w, 3), 255.0)
    rgb[hit] = np.einsum("nk,nkc->nc", bary[hit], colours[f].astype(np.float64))
    a, b, c = (cam[f[:, i]] for i in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-20)
    centre = (a + b + c) / 3
    light = np.abs(np.sum(normal * centre, 1)) / np.linalg.norm(centre, axis=1)  # facing the camera: bright
    shaded = np.full((h, w, 3), 255.0)
    shaded[hit] = (40 + 200 * light)[:, None]
    return rgb.clip(0, 255).astype(np.uint8), shaded.astype(np.uint8)


def sheet(panels: list[list[np.ndarray]], labels: list[str]) -> Image.Image:
    """Panels in a grid, each column labelled."""
    h, w = panels[0][0].shape[:2]
    out = Image.new("RGB", (w * len(panels[0]), h * len(panels)), "white")
    for r, row in enumerate(panels):
        for c, panel in enumerate(row):
            out.paste(Image.fromarray(panel), (c * w, r * h))
    draw = ImageDraw.Draw(out)
    for c, label in enumerate(labels):
        draw.text((c * w + 8, 6), label, fill=(0, 0, 0))
    return out


def viewpoint(frame, pull_back: float) -> Camera:
    """``frame``'s camera moved back along its viewing axis by ``pull_back`` metres (more of the scene in view)."""
    c2w = frame.camera.c2w64().copy()
    c2w[:3, 3] -= pull_back * c2w[:3, 2]
    return Camera(frame.camera.K64(), c2w, frame.camera.width, frame.camera.height)


def run_dataset(name: str, voxel: float, depth_max: float, repeats: int, out: Path, min_supports: list[float]) -> list[dict]:
    frames = list(load_dataset(DATA / name))
    split = interpolation_split(len(frames), [2])
    heldout = [frames[i] for i in split.heldout]
    inputs = [f for i, f in enumerate(frames) if i not in split.heldout]
    config = SceneConfig(voxel_size=voxel, range={"far": depth_max})
    scene, tsdf = Scene(config), Open3DTSDF(voxel, depth_max=depth_max)
    t0 = time.perf_counter()
    for f in inputs:
        scene.fold(f)
    fold_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for f in inputs:
        tsdf.integrate(f)
    integrate_s = time.perf_counter() - t0

    sums = scene.sums()
    surface_mesh(sums, config)  # compile / load the numba kernels outside the timing
    meshes = {}
    for min_support in min_supports:
        ours, ours_s = timed(lambda: surface_mesh(sums, config, min_support), repeats)
        label = "ours (mesh.ply)" + (f", min_support {min_support:g}" if min_support else "")
        meshes[label] = (ours.vertices.numpy(), ours.faces.numpy(), ours.colours.numpy(), ours_s, fold_s, len(scene))
    theirs, theirs_s = timed(lambda: tsdf.grid.extract_triangle_mesh().to_legacy(), repeats)
    meshes |= {
        "Open3D TSDF": (np.asarray(theirs.vertices), np.asarray(theirs.triangles),
                        np.clip(np.asarray(theirs.vertex_colors) * 255, 0, 255).astype(np.uint8), theirs_s, integrate_s,
                        len(tsdf.voxels()[0]) * 16**3),
    }
    points = np.concatenate([lifted(f, depth_max) for f in heldout])
    rng = np.random.default_rng(0)
    rows = []
    for method, (v, f, _, extract_s, fuse_s, voxels) in meshes.items():
        rows.append({"dataset": name, "method": method, "voxel mm": f"{voxel * 1000:g}",
                     "fuse s (all inputs)": f"{fuse_s:.1f}", "voxels (ours: occupied; Open3D: in its blocks)": voxels,
                     "extract s (median)": f"{extract_s:.2f}", "vertices": len(v), "faces": len(f),
                     **distances(v, f, points, heldout, voxel, depth_max, rng)})
    middle = heldout[len(heldout) // 2]
    view = viewpoint(middle, 0.3 * float(np.median(middle.depth.numpy()[middle.depth.numpy() > 0])))
    shown = [list(meshes)[0], "Open3D TSDF"]  # the default mesh and the peer's
    pictures = [picture(*meshes[label][:3], view) for label in shown]
    out.mkdir(parents=True, exist_ok=True)
    sheet([[p[0] for p in pictures], [p[1] for p in pictures]], shown).save(out / f"{name}.png")
    print(f"{name}: {len(inputs)} frames fused, held out {list(split.heldout)}, {len(points)} held-out points; "
          f"picture {out / f'{name}.png'}", flush=True)
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--datasets", nargs="+", default=["realsense_shelf:0.004:3", "sun3d_studyroom:0.01:4"],
                   help="NAME:VOXEL:DEPTH_MAX, NAME a folder of ../shared/data")
    p.add_argument("--repeats", type=int, default=3, help="timed extractions per mesh (median)")
    p.add_argument("--min-support", type=float, nargs="+", default=[0.0],
                   help="R_scene thresholds of our mesh, one row each (the first one is pictured)")
    p.add_argument("--out", type=Path, default=Path("docs/mesh"), help="folder of the pictures")
    args = p.parse_args(argv)
    print(machine_summary())
    rows = []
    for spec in args.datasets:
        name, voxel, depth_max = spec.split(":")
        rows += run_dataset(name, float(voxel), float(depth_max), args.repeats, args.out, args.min_support)
    print()
    print_table("Mesh export against Open3D's TSDF mesh (held-out depth; times: this machine, shared, noisy)", rows)


if __name__ == "__main__":
    main()
