"""A coloured triangle mesh of the scene's surface: marching cubes of its signed distance, block by block.

The distance is `surface`'s: built from the support and the representative geometry the scene
already holds (each voxel's point moments and view directions), no extra state. The lattice is cut
into cubic blocks of ``block`` cubes; each block with voxels near it gets a dense grid of its
``block + 1`` nodes a side, their distance, and scikit-image's marching cubes (Lewiner) over its
cubes. Neighbouring blocks share their boundary nodes, so a vertex on a shared face comes out of
both: vertices are merged by the lattice edge they lie on. Memory is the per-voxel arrays plus one
block's grid at a time (and the mesh), whatever the scene's extent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..config import SceneConfig
from .decoding import check_decode_arguments
from .selection import decoded_rows
from .scene import Scene
from .fields import unpack_keys
from .stored import HALF_FIELDS, raw_sums
from .surface import block_distance, blocks_of, pack_cells, tangent_planes, view_direction_sums, voxel_moments

_MESH_FIELDS = ("r_sum", "rep_pos", "pos_sum", "pos_sq", "rgb_sum", "sh_a")
# what a mesh reads of the sums: keys, the representative's colour, and those fields stored or as sums
MESH_SUMS = {"keys", "rep_rgb", *_MESH_FIELDS, *(HALF_FIELDS.get(name, name) for name in _MESH_FIELDS)}
DEFAULT_BLOCK = 32  # cubes per block edge: 33^3 nodes, a few MB of grids per block


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh in world coordinates (metres); faces wind counter-clockwise seen from the front
    (the side the cameras saw)."""

    vertices: Tensor  # [N, 3] float32
    faces: Tensor  # [F, 3] int64 vertex indices
    colours: Tensor  # [N, 3] uint8 RGB

    def __len__(self) -> int:
        return int(self.faces.shape[0])


def cube_mask(defined: np.ndarray) -> np.ndarray:  # [X, Y, Z] bool -> [X, Y, Z] bool
    """Marching cubes' mask: True at the upper corner of each cube whose eight corners are all defined
    (scikit-image's Lewiner code reads the mask at a cube's upper corner), so no face is made from
    cells with no distance."""
    both = defined[1:, 1:, 1:].copy()
    for step in np.ndindex(2, 2, 2):
        both &= defined[step[0]: defined.shape[0] - 1 + step[0], step[1]: defined.shape[1] - 1 + step[1],
                        step[2]: defined.shape[2] - 1 + step[2]]
    mask = np.zeros_like(defined)
    mask[1:, 1:, 1:] = both
    return mask


def trilinear(grid: np.ndarray, points: np.ndarray) -> np.ndarray:  # [X, Y, Z, C], [N, 3] -> [N, C]
    """Trilinear interpolation of a grid of nodes at points in node coordinates (inside the grid)."""
    top = np.array(grid.shape[:3]) - 1
    base = np.clip(np.floor(points).astype(np.int64), 0, np.maximum(top - 1, 0))
    f = points - base
    out = np.zeros((len(points), grid.shape[3]))
    for step in np.ndindex(2, 2, 2):
        corner = np.minimum(base + np.array(step), top)
        share = np.prod(np.where(np.array(step), f, 1.0 - f), 1)
        out += share[:, None] * grid[tuple(corner.T)]
    return out


def _block_surface(members, origin, cells, weight, point, normal, colour, block):
    """Marching cubes of one block: vertices (global node coordinates, float64), colours [0, 1], faces; None if it has none."""
    from skimage.measure import marching_cubes  # the service's extra; the library imports without it

    distance, defined, colours = block_distance(members, cells, origin, block + 1, weight, point, normal, colour)
    mask = cube_mask(defined)
    if not mask.any() or not (distance[defined] < 0).any() or not (distance[defined] > 0).any():
        return None
    volume = np.where(defined, distance, 1.0).astype(np.float32)  # masked cubes never read undefined nodes
    try:
        verts, faces, _, _ = marching_cubes(volume, 0.0, mask=mask, gradient_direction="descent")
    except RuntimeError:  # "No surface found": every sign change lies in masked cubes
        return None
    verts = verts.astype(np.float64)
    return verts + origin, trilinear(colours, verts), faces.astype(np.int64)


NODE_EPS = 1e-5  # of a voxel: a vertex this near a lattice node is on it (float32 rounding of the volume's fractions)


def merge_vertices(
    vertices: np.ndarray,  # [N, 3] float64 node coordinates
    faces: np.ndarray,  # [F, 3] int64
) -> tuple[np.ndarray, np.ndarray]:  # keep [K] int64 rows of vertices, faces [F', 3] over them
    """One vertex per lattice edge: marching cubes puts a vertex on the edge between two nodes, so
    the edge (its lower node and its axis) names it, and the copies that two blocks make of a vertex
    on their shared face become one. A vertex on a node (the surface through it exactly) lies on every
    edge that meets there, and rounding puts each edge's copy a hair to one side or the other: within
    `NODE_EPS` of a node, the node names it (axis 3). Faces that collapse are dropped."""
    lower = np.floor(vertices)
    upper = vertices - lower > 1 - NODE_EPS
    lower = (lower + upper).astype(np.int64)
    fraction = np.where(upper, 0.0, vertices - lower)
    axis = np.where(fraction.max(1) < NODE_EPS, 3, np.argmax(fraction, 1))
    key = pack_cells(lower)
    order = np.lexsort((axis, key))
    new = np.ones(len(order), bool)
    new[1:] = (key[order][1:] != key[order][:-1]) | (axis[order][1:] != axis[order][:-1])
    index = np.empty(len(order), np.int64)
    index[order] = np.cumsum(new) - 1
    faces = index[faces]
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return order[new], faces[good]


def surface_mesh(
    sums: dict[str, np.ndarray],  # a scene's sums (`Scene.sums`, `DecodeInputs.sums`), every row
    config: SceneConfig,
    min_support: float = 0.0,  # R_scene a voxel needs to count as surface, as for the Gaussians
    block: int = DEFAULT_BLOCK,  # cubes per block edge (>= 4)
) -> Mesh:
    """The scene's surface as a coloured triangle mesh (module docstring). The voxels that count are
    the ones that decode to Gaussians (`selection.decoded_rows`: support above ``min_support``, not
    seen through more than seen); each weighs by its R_scene. An empty scene gives an empty mesh.

    Example:
        >>> from canonical_core.scene import Scene
        >>> len(surface_mesh(Scene(SceneConfig(voxel_size=0.01)).sums(), SceneConfig(voxel_size=0.01)))
        0
    """
    if isinstance(block, bool) or not isinstance(block, int) or block < 4:
        raise ValueError(f"block: expected an integer of at least 4, got {block!r}")
    check_decode_arguments(None, min_support)  # as a decode takes it: NaN would read as no support anywhere
    chosen = decoded_rows(sums, min_support, config)
    rows = chosen.rows
    empty = Mesh(torch.zeros((0, 3)), torch.zeros((0, 3), dtype=torch.int64), torch.zeros((0, 3), dtype=torch.uint8))
    if not len(rows):
        return empty
    # the fields a mesh reads, as float32 sums (`stored.raw_sums`; a batch reference's sums as they are)
    picked = raw_sums({name: array[rows] for name, array in sums.items() if name in MESH_SUMS})
    view = view_direction_sums(picked["sh_a"])
    cells = unpack_keys(torch.from_numpy(picked["keys"])).numpy()
    mean, second, colour = voxel_moments(picked, config.research.eps)
    # R_scene is the total weight of a voxel's points: weighted by it, pooled moments are the points' own
    weight = chosen.support.numpy().astype(np.float64) + config.research.eps
    normal, point = tangent_planes(cells, weight, mean, second, view, block)
    groups = blocks_of(cells, block, 1, 2)  # a block's nodes are cells b * block .. (b + 1) * block; each reads 3x3x3
    vertices, colours, faces, count = [], [], [], 0
    for g in range(len(groups.origins)):
        part = _block_surface(groups.members[groups.starts[g]: groups.starts[g + 1]], groups.origins[g], cells, weight,
                              point, normal, colour, block)
        if part is not None:
            vertices.append(part[0])
            colours.append(part[1])
            faces.append(part[2] + count)
            count += len(part[0])
    if not faces:
        return empty
    keep, merged = merge_vertices(np.concatenate(vertices), np.concatenate(faces))
    world = (np.concatenate(vertices)[keep] + 0.5) * config.voxel_size  # node j is the centre of cell j
    rgb = np.clip(np.rint(np.concatenate(colours)[keep] * 255.0), 0, 255).astype(np.uint8)
    return Mesh(torch.from_numpy(world.astype(np.float32)), torch.from_numpy(merged), torch.from_numpy(rgb))


def scene_mesh(scene: Scene, min_support: float = 0.0) -> Mesh:
    """`surface_mesh` of a live scene: its sums are copied under the scene's lock (`Scene.decode_inputs`)
    and meshed outside it, so folds go on meanwhile."""
    return surface_mesh(scene.decode_inputs().sums, scene.config, min_support)


def mesh_ply_bytes(mesh: Mesh) -> bytes:
    """Binary little-endian PLY: vertices (float x, y, z; uchar red, green, blue) and faces (a uchar
    count and int vertex_indices), the layout MeshLab, Open3D, Blender and CAD importers read."""
    n, f = len(mesh.vertices), len(mesh.faces)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment CanonicalGS Fusion surface mesh\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {f}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    vertex = np.empty(n, [("xyz", "<f4", 3), ("rgb", "u1", 3)])
    vertex["xyz"], vertex["rgb"] = mesh.vertices.numpy(), mesh.colours.numpy()
    face = np.empty(f, [("count", "u1"), ("index", "<i4", 3)])
    face["count"], face["index"] = 3, mesh.faces.numpy()
    return header + vertex.tobytes() + face.tobytes()
