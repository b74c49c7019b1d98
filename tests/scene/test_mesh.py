"""The surface mesh: marching cubes of the signed distance from the scene's voxels (`scene.mesh`, `scene.surface`).

The scene is folded from ray-cast RGB-D frames of a known surface (a sphere in front of a wall), so
the mesh can be held to the true geometry and colours.
"""

from __future__ import annotations

import numpy as np
import pytest

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.datasets.synthetic import look_at
from canonical_core.scene import Scene
from canonical_core.scene.mesh import Mesh, cube_mask, mesh_ply_bytes, merge_vertices, surface_mesh
from canonical_core.scene.surface import blocks_of
from tests.mesh_ply import parse_mesh_ply

VOXEL = 0.02
RADIUS = 0.25  # the sphere, at the origin: red above z = 0, blue below
WALL_Y = 0.6  # the wall: the plane y = WALL_Y, |x|, |z| <= WALL_HALF, grey
WALL_HALF = 0.8
RED, BLUE, GREY = (220, 30, 30), (30, 30, 220), (128, 128, 128)


def ray_cast(camera: Camera) -> tuple[np.ndarray, np.ndarray]:  # rgb [H, W, 3] uint8, depth [H, W] float32
    """The sphere and the wall seen by ``camera``: colour and z-depth of each pixel centre (0 = nothing)."""
    K, c2w = camera.K64(), camera.c2w64()
    v, u = np.meshgrid(np.arange(camera.height, dtype=np.float64), np.arange(camera.width, dtype=np.float64), indexing="ij")
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    b = rays @ o
    a = np.sum(rays * rays, -1)
    disc = b * b - a * (o @ o - RADIUS**2)
    t_sphere = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
    t_wall = np.where(rays[..., 1] > 0, (WALL_Y - o[1]) / np.where(rays[..., 1] > 0, rays[..., 1], 1.0), np.inf)
    hit_wall = o + t_wall[..., None] * rays
    t_wall = np.where((np.abs(hit_wall[..., 0]) <= WALL_HALF) & (np.abs(hit_wall[..., 2]) <= WALL_HALF), t_wall, np.inf)
    t = np.minimum(t_sphere, t_wall)
    upper = (o + t_sphere[..., None] * rays)[..., 2] > 0
    rgb = np.where((t_sphere <= t_wall)[..., None], np.where(upper[..., None], RED, BLUE), GREY)
    rgb = np.where(np.isfinite(t)[..., None], rgb, 0).astype(np.uint8)
    return rgb, np.where(np.isfinite(t), t, 0.0).astype(np.float32)


def true_distance(points: np.ndarray) -> np.ndarray:  # [N, 3] -> [N] metres to the nearer of the two surfaces
    sphere = np.abs(np.linalg.norm(points, axis=1) - RADIUS)
    outside = np.maximum(np.abs(points[:, [0, 2]]) - WALL_HALF, 0.0)
    wall = np.sqrt((points[:, 1] - WALL_Y) ** 2 + np.sum(outside**2, 1))
    return np.minimum(sphere, wall)


@pytest.fixture(scope="module")
def scene() -> Scene:
    width, height = 160, 120
    K = [[140.0, 0.0, (width - 1) / 2], [0.0, 140.0, (height - 1) / 2], [0.0, 0.0, 1.0]]
    s = Scene(SceneConfig(voxel_size=VOXEL))
    for i, angle in enumerate(np.linspace(-0.9, 0.9, 7)):
        eye = (1.3 * np.sin(angle), -1.3 * np.cos(angle), 0.35 * np.cos(2 * angle))
        camera = Camera(K, look_at(eye, (0.0, 0.0, 0.0)), width, height)
        rgb, depth = ray_cast(camera)
        s.fold(Frame(rgb=rgb, camera=camera, depth=depth, frame_id=f"{i}"))
    return s


@pytest.fixture(scope="module")
def mesh(scene) -> Mesh:
    return surface_mesh(scene.sums(), scene.config)


def test_vertices_lie_within_a_voxel_of_the_true_surface(mesh):
    assert len(mesh) > 1000
    d = true_distance(mesh.vertices.numpy().astype(np.float64))
    assert np.median(d) < 0.25 * VOXEL
    assert np.quantile(d, 0.99) < VOXEL, np.quantile(d, [0.5, 0.9, 0.99, 1.0])


def test_the_sphere_and_the_wall_are_covered(mesh):
    v = mesh.vertices.numpy()
    on_sphere = np.abs(np.linalg.norm(v, axis=1) - RADIUS) < VOXEL
    front = on_sphere & (v[:, 1] < -0.1)  # the side the cameras saw
    area = 2 * np.pi * RADIUS**2 * (1 - 0.1 / RADIUS)  # the cap y < -0.1
    # a surface sampled at about a voxel's spacing has about one vertex per voxel face it crosses
    assert front.sum() > 0.5 * area / VOXEL**2
    on_wall = np.abs(v[:, 1] - WALL_Y) < VOXEL
    assert np.ptp(v[on_wall, 0]) > WALL_HALF and np.ptp(v[on_wall, 2]) > WALL_HALF


def test_the_mesh_is_a_closed_up_surface_where_seen(mesh):
    faces = mesh.faces.numpy()
    assert faces.min() >= 0 and faces.max() < len(mesh.vertices)
    assert len(np.unique(np.sort(faces, 1), axis=0)) == len(faces)  # no face twice
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert uses.max() <= 2  # edge-manifold: no seam where blocks meet (an edge used once is the rim)
    assert (uses == 2).mean() > 0.95
    # Euler characteristic of a few open sheets: near 0 per sheet, nothing like the thousands of a torn mesh
    assert abs(len(mesh.vertices) - len(uses) + len(faces)) < 20


def test_faces_face_the_cameras(mesh):
    v, f = mesh.vertices.numpy().astype(np.float64), mesh.faces.numpy()
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    normal = np.cross(b - a, c - a)
    centre = (a + b + c) / 3
    on_sphere = np.abs(np.linalg.norm(centre, axis=1) - RADIUS) < 0.5 * VOXEL
    outward = np.sum(normal[on_sphere] * centre[on_sphere], 1) > 0
    assert outward.mean() > 0.97
    on_wall = (np.abs(centre[:, 1] - WALL_Y) < 0.5 * VOXEL) & (np.abs(centre[:, 0]) < 0.5)
    assert (normal[on_wall, 1] < 0).mean() > 0.97  # toward the cameras, at y < 0


def test_vertex_colours_are_the_surface_colours(mesh):
    v, rgb = mesh.vertices.numpy(), mesh.colours.numpy().astype(np.int64)
    on_sphere = np.abs(np.linalg.norm(v, axis=1) - RADIUS) < VOXEL
    upper, lower = on_sphere & (v[:, 2] > 2 * VOXEL), on_sphere & (v[:, 2] < -2 * VOXEL)
    wall = (np.abs(v[:, 1] - WALL_Y) < VOXEL) & (np.linalg.norm(v[:, [0, 2]], axis=1) > RADIUS + 3 * VOXEL)
    for where, colour in ((upper, RED), (lower, BLUE), (wall, GREY)):
        assert where.sum() > 100
        assert np.median(np.abs(rgb[where] - colour).max(1)) <= 3, colour


def test_small_blocks_give_the_same_mesh(scene, mesh):
    small = surface_mesh(scene.sums(), scene.config, block=8)  # the sphere spans dozens of blocks
    np.testing.assert_allclose(small.vertices.numpy(), mesh.vertices.numpy(), atol=1e-6)
    assert np.array_equal(small.colours.numpy(), mesh.colours.numpy())
    as_set = lambda f: np.unique(np.sort(f.numpy(), 1), axis=0)  # noqa: E731
    assert np.array_equal(as_set(small.faces), as_set(mesh.faces))


def test_min_support_keeps_the_better_supported_surface(scene, mesh):
    sums = scene.sums()
    strict = surface_mesh(sums, scene.config, min_support=float(np.quantile(sums["r_sum"], 0.5)))
    assert 0 < len(strict) < len(mesh)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), "1"])
def test_min_support_is_checked_as_a_decode_checks_it(scene, bad):
    with pytest.raises(ValueError, match="^min_support: expected >= 0"):
        surface_mesh(scene.sums(), scene.config, min_support=bad)


def test_ply_holds_the_mesh(mesh):
    xyz, rgb, faces = parse_mesh_ply(mesh_ply_bytes(mesh))
    assert np.array_equal(xyz, mesh.vertices.numpy())
    assert np.array_equal(rgb, mesh.colours.numpy())
    assert np.array_equal(faces, mesh.faces.numpy())


def test_an_empty_scene_has_an_empty_mesh():
    config = SceneConfig(voxel_size=VOXEL)
    mesh = surface_mesh(Scene(config).sums(), config)
    assert len(mesh) == 0 and mesh.vertices.shape == (0, 3)
    xyz, rgb, faces = parse_mesh_ply(mesh_ply_bytes(mesh))
    assert len(xyz) == len(faces) == 0


def test_bad_arguments_name_their_field(scene):
    for block in (3, 0, 8.0, True):
        with pytest.raises(ValueError, match="^block: "):
            surface_mesh(scene.sums(), scene.config, block=block)
    flat = SceneConfig(voxel_size=VOXEL, sh_degree=0)
    no_directions = Scene(flat)
    no_directions.fold(next(iter([Frame(rgb=np.zeros((8, 8, 3), np.uint8), camera=Camera(
        [[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]], np.eye(4), 8, 8), depth=np.ones((8, 8), np.float32))])))
    with pytest.raises(ValueError, match="^sh_degree: "):
        surface_mesh(no_directions.sums(), flat)


@pytest.mark.parametrize("before, after", [(1, 2), (2, 2), (0, 0)])
def test_every_voxel_is_in_each_block_whose_grid_holds_it(before, after):
    block = 8
    cells = np.array([[0, 0, 0], [7, 8, 9], [-3, 10, -9], [1, 5, 2], [15, -17, 6]])
    groups = blocks_of(cells, block, before, after)
    for r, cell in enumerate(cells):
        expected = {b for b in np.ndindex(6, 6, 6) if all(
            (bb - 3) * block - before <= c <= (bb - 2) * block - 1 + after for bb, c in zip(b, cell))}
        got = {tuple(int(x) // block + 3 for x in groups.origins[g]) for g in range(len(groups.origins))
               if r in groups.members[groups.starts[g]: groups.starts[g + 1]]}
        assert got == expected
    assert len({tuple(o) for o in groups.origins}) == len(groups.origins)  # each block once


def test_cube_mask_marks_cubes_with_every_corner_defined():
    defined = np.ones((4, 4, 4), bool)
    defined[0, 0, 0] = False
    mask = cube_mask(defined)
    assert not mask[0].any() and not mask[:, 0].any() and not mask[:, :, 0].any()  # no cube's upper corner
    assert not mask[1, 1, 1]  # the cube with the undefined corner
    assert mask[1:, 1:, 1:].sum() == 26


def test_copies_of_a_vertex_on_one_lattice_edge_merge():
    vertices = np.array([[2.25, 3.0, 4.0], [2.25000002, 3.0, 4.0], [2.0, 3.5, 4.0], [2.0, 3.0, 4.5]])
    keep, faces = merge_vertices(vertices, np.array([[0, 2, 3], [1, 3, 2], [0, 1, 2]]))
    assert len(keep) == 3  # vertex 1 is vertex 0's copy (the same edge along x)
    assert faces.tolist() == [[0, 1, 2], [0, 2, 1]]  # the face over both copies collapsed and went


def test_copies_of_a_vertex_on_a_lattice_node_merge_whichever_edge_made_them():
    """The surface through a node: the edges meeting there each put a copy on it, rounded a hair
    above or below it (3.0 as 2.9999999 along y, 4.0000001 along z); one vertex, no sliver faces."""
    vertices = np.array([[2.0, 3.0, 4.0], [2.0, 2.9999999, 4.0], [2.0, 3.0, 4.0000001],
                         [2.5, 3.0, 4.0], [2.0, 3.5, 4.0]])
    keep, faces = merge_vertices(vertices, np.array([[0, 1, 2], [1, 3, 4], [2, 4, 3]]))
    assert len(keep) == 3 and np.abs(vertices[keep[2]] - [2, 3, 4]).max() < 1e-6  # the node's copies are one
    assert faces.tolist() == [[2, 0, 1], [2, 1, 0]]  # the sliver over the copies went
