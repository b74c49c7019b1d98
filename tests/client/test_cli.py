"""The ``canonical`` CLI (in-process ``main``) against a real service started by ``canonical serve``."""

from __future__ import annotations

import numpy as np
from PIL import Image

from canonical_core import load_ply
from client import cli


def test_commands_are_a_registry():
    assert {"serve", "stream", "render", "export", "sessions"} <= set(cli.COMMANDS)
    args = cli.build_parser().parse_args(["stream", "some/dataset", "--voxel-size", "0.01", "--url", "http://x"])
    assert args.command == "stream" and args.voxel_size == 0.01


def test_stream_render_export_sessions(server, shelf_dir, tmp_path, capsys):
    url = ["--url", server.url]
    assert cli.main(["stream", str(shelf_dir), *url, "--voxel-size", "0.008", "--stride", "10", "--max-frames", "3",
                     "--scale", "0.5"]) == 0
    out, err = capsys.readouterr()
    assert "3 frames in" in out and "frames/s" in out
    session_id = next(line.split()[1] for line in err.splitlines() if line.startswith("session "))

    assert cli.main(["stream", str(shelf_dir), *url, "--session", session_id, "--stride", "10", "--max-frames", "1",
                     "--scale", "0.5"]) == 0
    assert "4 frames" in capsys.readouterr().out

    assert cli.main(["sessions", *url]) == 0
    listing = capsys.readouterr().out
    assert session_id in listing and " 4 " in listing

    png = tmp_path / "like.png"
    assert cli.main(["render", *url, "--session", session_id, "--frame-like", f"{shelf_dir}:0", "-o", str(png)]) == 0
    assert Image.open(png).size == (640, 480)  # the dataset frame's own camera

    pose = tmp_path / "pose.txt"
    np.savetxt(pose, np.eye(4))
    small = tmp_path / "pose.png"
    assert cli.main(["render", *url, "--session", session_id, "--pose", str(pose), "--K", "150,150,79.5,59.5",
                     "--width", "160", "--height", "120", "--background", "1,1,1", "-o", str(small)]) == 0
    assert Image.open(small).size == (160, 120)

    ply, splat = tmp_path / "scene.ply", tmp_path / "scene.splat"
    assert cli.main(["export", *url, "--session", session_id, "-o", str(ply)]) == 0
    assert cli.main(["export", *url, "--session", session_id, "-o", str(splat)]) == 0
    assert splat.stat().st_size == 32 * len(load_ply(ply)) > 0
    capsys.readouterr()

    assert cli.main(["export", *url, "--session", "no-such-session", "-o", str(ply)]) == 1
    assert "404" in capsys.readouterr().err
