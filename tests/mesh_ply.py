"""Reading the surface mesh's PLY in the tests, from the header's own words (the PLY format), not the writer's code."""

from __future__ import annotations

import numpy as np


def parse_mesh_ply(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz [N, 3] float32, rgb [N, 3] uint8, faces [F, 3] int32 of the layout `mesh_ply_bytes` writes,
    read by the header's own words (the PLY format), not by the writer's code."""
    head, _, body = data.partition(b"end_header\n")
    lines = head.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    props = [line for line in lines if line.startswith("property")]
    assert props == ["property float x", "property float y", "property float z", "property uchar red",
                     "property uchar green", "property uchar blue", "property list uchar int vertex_indices"]
    n = int(next(line for line in lines if line.startswith("element vertex")).split()[2])
    f = int(next(line for line in lines if line.startswith("element face")).split()[2])
    vertex = np.frombuffer(body, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]), n)
    face = np.frombuffer(body, np.dtype([("n", "u1"), ("i", "<i4", 3)]), f, offset=vertex.nbytes)
    assert len(body) == vertex.nbytes + face.nbytes and (face["n"] == 3).all()
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], 1)
    return xyz, np.stack([vertex["r"], vertex["g"], vertex["b"]], 1), face["i"]
