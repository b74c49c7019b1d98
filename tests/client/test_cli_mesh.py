"""``canonical export --mesh`` (in-process ``main``) against a real service started by ``canonical serve``."""

from __future__ import annotations

import pytest

from client import cli
from tests.mesh_ply import parse_mesh_ply


@pytest.mark.realdata
def test_export_mesh(server, shelf_dir, tmp_path, capsys):
    url = ["--url", server.url]
    assert cli.main(["stream", str(shelf_dir), *url, "--voxel-size", "0.01", "--stride", "10", "--max-frames", "3",
                     "--scale", "0.5"]) == 0
    session_id = capsys.readouterr().out.strip()

    out = tmp_path / "surface.ply"
    assert cli.main(["export", *url, "--session", session_id, "--mesh", "-o", str(out)]) == 0
    assert capsys.readouterr().out == f"{out}\n"
    xyz, rgb, faces = parse_mesh_ply(out.read_bytes())
    assert len(xyz) > 1000 and len(faces) > len(xyz) and faces.max() < len(xyz)
    assert 0.2 < xyz[:, 2].mean() < 1.0  # the shelf stands about half a metre in front of the first camera
    assert rgb.std() > 10  # coloured, not one flat colour

    for args, problem in ((["-o", str(tmp_path / "surface.splat")], "-o: expected a .ply file name"),
                          (["--max-gaussians", "100", "-o", str(out)], "--max-gaussians: ")):
        assert cli.main(["export", *url, "--session", session_id, "--mesh", *args]) == 2  # a usage error
        err = capsys.readouterr().err
        assert err.startswith(f"error: {problem}") and err.count("\n") == 1, err
    assert cli.main(["export", *url, "--session", "no-such-session", "--mesh", "-o", str(tmp_path / "x.ply")]) == 1
    assert "404" in capsys.readouterr().err and not (tmp_path / "x.ply").exists()
