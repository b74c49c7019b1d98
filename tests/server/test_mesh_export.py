"""GET /v1/sessions/{id}/mesh.ply against a real service process, on real shelf frames."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from scipy.spatial import cKDTree

from client.sdk import CanonicalError
from tests.mesh_ply import parse_mesh_ply

from .harness import TOKEN, VOXEL

pytestmark = pytest.mark.slow
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def world_points(kwargs: dict) -> tuple[np.ndarray, np.ndarray]:  # [N, 3] sensor depth lifted to world, [N, 3] its colours
    depth, K, c2w = kwargs["depth"], kwargs["K"], kwargs["c2w"]
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], 1)
    return cam @ c2w[:3, :3].T + c2w[:3, 3], kwargs["rgb"][v, u]


@pytest.mark.realdata
def test_mesh_ply_of_real_frames(client, server, frames, tmp_path):
    session = client.create_session(voxel_size=VOXEL)
    url = f"{server.url}/v1/sessions/{session.id}/mesh.ply"
    empty = httpx.get(url, headers=AUTH)
    assert empty.status_code == 409, empty.text
    assert empty.json()["error"]["code"] == "no_surface" and empty.json()["error"]["field"] == "frames"
    for kwargs in frames:
        session.add_frame(**kwargs)

    r = httpx.get(url, headers=AUTH, timeout=120)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/octet-stream"
    assert r.headers["content-disposition"] == f'attachment; filename="{session.id}.mesh.ply"'
    xyz, rgb, faces = parse_mesh_ply(r.content)
    assert len(xyz) == int(r.headers["x-canonical-vertices"]) > 1000
    assert len(faces) == int(r.headers["x-canonical-faces"]) > len(xyz)
    assert faces.min() >= 0 and faces.max() < len(xyz)

    # the mesh lies on what the sensor saw, and covers what frame 0 saw of it
    seen = [world_points(kwargs) for kwargs in frames]
    points, colours = np.concatenate([p for p, _ in seen]), np.concatenate([c for _, c in seen])
    gap, nearest = cKDTree(points).query(xyz.astype(np.float64))
    assert np.median(gap) < 0.5 * VOXEL, np.quantile(gap, [0.5, 0.9])
    cover, _ = cKDTree(xyz).query(seen[0][0])
    assert np.median(cover) < VOXEL and np.quantile(cover, 0.9) < 3 * VOXEL, np.quantile(cover, [0.5, 0.9])
    # vertex colours are the colours the camera saw there
    assert np.median(np.abs(rgb.astype(np.int64) - colours[nearest]).mean(1)) < 25

    # the SDK writes the same bytes; a stricter support threshold keeps part of the surface
    assert session.export_mesh(tmp_path / "surface.ply").read_bytes() == r.content
    strict = session.export_mesh(tmp_path / "strict.ply", min_support=1.0)
    assert 0 < len(parse_mesh_ply(strict.read_bytes())[2]) < len(faces)

    for value in ("-1", "nan", "inf", "many"):
        bad = httpx.get(url, params={"min_support": value}, headers=AUTH)
        assert bad.status_code == 422 and bad.json()["error"]["field"] == "min_support", (value, bad.text)
    none_left = httpx.get(url, params={"min_support": 1e12}, headers=AUTH, timeout=120)
    error = none_left.json()["error"]  # the frames made a surface: the threshold asked for is what leaves none
    assert none_left.status_code == 409 and error["field"] == "min_support" and "reaches 1e+12" in error["message"], error
    with pytest.raises(CanonicalError, match="404"):
        client.session("no-such-session").export_mesh(tmp_path / "x.ply")
    assert not (tmp_path / "x.ply").exists()
    assert session.digest()["frames"] == len(frames)  # reading the mesh changed nothing


@pytest.mark.realdata
def test_a_session_without_view_directions_is_told_why(client, server, frames):
    session = client.create_session(voxel_size=VOXEL, sh_degree=0)
    session.add_frame(**frames[0])
    r = httpx.get(f"{server.url}/v1/sessions/{session.id}/mesh.ply", headers=AUTH, timeout=120)
    assert r.status_code == 422 and r.json()["error"]["field"] == "sh_degree", r.text
