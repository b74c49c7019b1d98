"""The ``canonical`` CLI (in-process ``main``) against a real service started by ``canonical serve``."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from canonical_core import Camera, Frame, load_ply
from canonical_core.datasets import load_tsdf_fusion, synthetic_rgbd, write_tsdf_fusion
from client import cli
from client.cli import demo
from client.cli.capture import frame_arrays
from client.cli.launch import free_port, start_service
from client.sdk import Client

from ..conftest import DATA, require_capture

REPO = Path(__file__).resolve().parents[2]


def test_commands_are_a_registry():
    assert {"serve", "stream", "render", "export", "sessions"} <= set(cli.COMMANDS)
    args = cli.build_parser().parse_args(["stream", "some/dataset", "--voxel-size", "0.01", "--url", "http://x"])
    assert args.command == "stream" and args.voxel_size == 0.01


@pytest.mark.realdata
def test_stream_shows_each_fold_warning_once_a_figure_it_advises_and_the_last_word_in_its_summary(
        server, apc_bins_path, capsys):
    # the labels bin's depth under about 0.24 m disagrees from frame to frame: several frames are warned,
    # with shares and counts that change every frame (not shown again) and an advised near limit that
    # falls once more of the bin's floor was compared (shown again); the summary gives the stream's last
    assert cli.main(["stream", str(apc_bins_path / "bin_labels"), "--url", server.url, "--voxel-size", "0.01"]) == 0
    err = capsys.readouterr().err
    shown = [line for line in err.splitlines() if "working range" in line]
    advised = [re.search(r"range\.near=([0-9.]+) ignores", line).group(1) for line in shown]
    assert all(line.startswith("frame ") for line in shown) and len(advised) == len(set(advised)) >= 1
    summary = err.strip().splitlines()[-1]
    assert f"depth under {advised[-1]} m disagrees between frames (range.near={advised[-1]} ignores it)" in summary
    assert 0.2 < float(advised[-1]) <= 0.25


@pytest.mark.realdata
def test_stream_and_render_take_the_intrinsics_a_capture_lacks_from_K(server, capsys, tmp_path):
    capture = str(require_capture(DATA / "slambook_rgbd5"))  # a TUM capture without an intrinsics file
    url = ["--url", server.url, "--voxel-size", "0.02"]
    assert cli.main(["stream", capture, *url]) == 2
    assert "error: --K: " in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse's own usage error
        cli.main(["stream", capture, *url, "--K", "518,519,325.5"])
    assert "argument --K: expected fx,fy,cx,cy" in capsys.readouterr().err
    assert cli.main(["stream", capture, *url, "--K", "518,519,325.5,253.5"]) == 0
    out = capsys.readouterr()
    assert "5 frames in" in out.err and Client(server.url).session(out.out.strip()).stats()["frames"] == 5
    # a view at one of its frames takes the capture's intrinsics the same way
    session = ["--url", server.url, "--session", out.out.strip()]
    assert cli.main(["render", *session, "--frame-like", f"{capture}:2", "-o", str(tmp_path / "x.png")]) == 2
    assert "--frame-like: " in (err := capsys.readouterr().err) and "(here: --K fx,fy,cx,cy)" in err
    assert cli.main(["render", *session, "--frame-like", f"{capture}:2", "--K", "518,519,325.5,253.5",
                     "-o", str(tmp_path / "like.png")]) == 0
    (tmp_path / "pose.txt").write_text((Path(capture) / "pose.txt").read_text().splitlines()[2] + "\n")
    assert cli.main(["render", *session, "--pose", str(tmp_path / "pose.txt"), "--K", "518,519,325.5,253.5",
                     "--size", "640x480", "-o", str(tmp_path / "posed.png")]) == 0
    assert (tmp_path / "like.png").read_bytes() == (tmp_path / "posed.png").read_bytes()


@pytest.mark.realdata
def test_streaming_a_capture_and_rendering_at_its_frames_never_load_torch_or_numba(server, shelf_dir, tmp_path):
    # the capture's PNGs travel as they are and a render at one of its frames needs only its camera, so
    # the CLI does both without torch and numba, which would take most of its start-up and memory; nor
    # without --set the settings' definitions (pydantic models, slow to import)
    url = ["--url", server.url]
    stream = ["stream", str(shelf_dir), *url, "--voxel-size", "0.01", "--stride", "25", "--max-frames", "2"]
    render = ["render", *url, "--frame-like", f"{shelf_dir}:1", "-o", str(tmp_path / "view.png"), "--session"]
    probe = ("import contextlib, io, sys\n"
             "from client import cli\n"
             "out = io.StringIO()\n"
             "with contextlib.redirect_stdout(out):\n"
             f"    streamed = cli.main({stream!r})\n"
             f"rendered = cli.main({render!r} + [out.getvalue().strip()])\n"
             "print(streamed, rendered, {'torch', 'numba', 'pydantic'} & set(sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", probe], cwd=Path(__file__).resolve().parents[2], capture_output=True,
                         text=True, timeout=120)
    assert out.stdout.split()[-3:] == ["0", "0", "set()"], out.stderr
    assert "2 frames in" in out.stderr and Image.open(tmp_path / "view.png").size == (640, 480)


@pytest.mark.realdata
def test_stream_render_export_sessions(server, shelf_dir, tmp_path, capsys):
    url = ["--url", server.url]
    assert cli.main(["stream", str(shelf_dir), *url, "--voxel-size", "0.008", "--stride", "10", "--max-frames", "3",
                     "--scale", "0.5"]) == 0
    out, err = capsys.readouterr()
    assert "3 frames in" in err and "frames/s" in err
    session_id = out.strip()  # the id alone on stdout

    # resumes after the session's 3 frames: sends only the 4th
    assert cli.main(["stream", str(shelf_dir), *url, "--session", session_id, "--stride", "10", "--max-frames", "4",
                     "--scale", "0.5"]) == 0
    out, err = capsys.readouterr()
    assert out.strip() == session_id and "1 frames in" in err and "4 frames" in err

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
    composited = tmp_path / "composited.png"
    assert cli.main(["render", *url, "--session", session_id, "--frame-like", f"{shelf_dir}:0", "--colour", "composited",
                     "-o", str(composited)]) == 0
    plain, bright = (np.asarray(Image.open(p), dtype=np.int16) for p in (composited, png))
    assert (bright >= plain - 1).all() and (bright > plain + 8).any()  # partly covered pixels are no longer darkened

    ply, splat = tmp_path / "scene.ply", tmp_path / "scene.splat"
    assert cli.main(["export", *url, "--session", session_id, "-o", str(ply)]) == 0
    assert cli.main(["export", *url, "--session", session_id, "-o", str(splat)]) == 0
    assert splat.stat().st_size == 32 * len(load_ply(ply)) > 0
    capsys.readouterr()

    assert cli.main(["export", *url, "--session", "no-such-session", "-o", str(ply)]) == 1
    assert "404" in capsys.readouterr().err


@pytest.mark.realdata
def test_scaled_frames_keep_their_labels_features_and_depth_std():
    """--scale: depth_std resized as its depth is (nearest), labels and features sent at their own
    resolution, which a frame takes at any size (class ids stay ids)."""
    camera = Camera(np.array([[8.0, 0, 3.5], [0, 8, 3.5], [0, 0, 1]]), np.eye(4), 8, 8)
    depth = np.arange(1, 65, dtype=np.float32).reshape(8, 8) / 32
    classes = np.arange(64, dtype=np.int64).reshape(8, 8) % 3
    frame = Frame(rgb=np.zeros((8, 8, 3), np.uint8), camera=camera, depth=depth, depth_std=depth / 100,
                  features=np.ones((4, 4, 2), np.float32), labels=classes, num_classes=3, frame_id="f")
    sent = frame_arrays(frame, 0.5)
    assert sent["rgb"].shape == (4, 4, 3) and sent["depth"].shape == sent["depth_std"].shape == (4, 4)
    assert np.array_equal(sent["depth_std"], sent["depth"] / 100)  # the same pixels as the depth's
    assert np.array_equal(sent["labels"], classes) and sent["num_classes"] == 3
    assert sent["features"].shape == (4, 4, 2)


@pytest.mark.realdata
def test_a_scaled_stream_fuses_the_captures_labels(server, apc_bins_path):
    streamed = subprocess.run([sys.executable, "-m", "client.cli", "stream", str(apc_bins_path / "bin_labels"), "--url",
                               server.url, "--voxel-size", "0.01", "--stride", "5", "--scale", "0.5", "--json"],
                              cwd=REPO, capture_output=True, text=True, timeout=300)
    assert streamed.returncode == 0, streamed.stderr
    assert json.loads(streamed.stdout)["label_dim"] == 3


@pytest.mark.realdata
def test_render_writes_each_map_as_a_png_or_as_its_values(server, apc_bins_path, tmp_path, capsys):
    """``--map`` depth, labels and features: PNGs a person or another tool reads (16-bit depth in
    millimetres, a palette label map), or with .npy the map's own values, each the other's twin."""
    url = ["--url", server.url]
    assert cli.main(["stream", str(apc_bins_path / "bin_labels"), *url, "--voxel-size", "0.008", "--stride", "4"]) == 0
    session = capsys.readouterr().out.strip()
    view = [*url, "--session", session, "--frame-like", f"{apc_bins_path / 'bin_labels'}:6"]
    for kind in ("depth", "labels", "features"):
        for suffix in ("png", "npy"):
            assert cli.main(["render", *view, "--map", kind, "-o", str(tmp_path / f"{kind}.{suffix}")]) == 0
    capsys.readouterr()

    metres = np.load(tmp_path / "depth.npy")
    millimetres = np.asarray(Image.open(tmp_path / "depth.png"))
    assert metres.dtype == np.float32 and metres.shape == millimetres.shape == (480, 640)
    drawn = metres > 0
    assert drawn.mean() > 0.5 and 0.2 < np.median(metres[drawn]) < 1.0  # a bin seen from about half a metre
    assert np.array_equal(millimetres, np.rint(metres * 1000).astype(np.uint16))

    classes = np.load(tmp_path / "labels.npy")
    palette = np.asarray(Image.open(tmp_path / "labels.png"))  # index 0 nothing drawn, k + 1 class k
    assert classes.dtype == np.int16 and np.array_equal(palette.astype(np.int16) - 1, classes)
    assert set(np.unique(classes)) == {-1, 0, 1, 2}  # the bin's three classes, and pixels nothing covers

    features = np.load(tmp_path / "features.npy")
    assert features.dtype == np.float16 and features.shape[:2] == (480, 640) and features.shape[2] > 1
    assert Image.open(tmp_path / "features.png").size == (640, 480)

    assert cli.main(["render", *view, "--map", "depth", "--colour", "composited", "-o", str(tmp_path / "x.png")]) == 2
    assert "--colour: only with --map rgb" in capsys.readouterr().err
    assert cli.main(["render", *view, "--map", "depth", "-o", str(tmp_path / "x.jpg")]) == 2
    assert "-o: expected .png files" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "x.jpg").exists()


@pytest.mark.realdata
def test_stream_sets_the_new_sessions_settings(server, shelf_dir, capsys):
    url = ["--url", server.url]
    assert cli.main(["stream", str(shelf_dir), *url, "--voxel-size", "0.01", "--stride", "20", "--max-frames", "2",
                     "--scale", "0.25", "--set", "colour_solve.views=2", "--set", "free_space.margin=3",
                     "--set", "depth.completion=true", "--set", "depth.sources=1"]) == 0
    session_id = capsys.readouterr().out.strip()
    config = Client(server.url).session(session_id).stats()["config"]
    assert (config["colour_solve"]["views"], config["free_space"]["margin"], config["depth"]["completion"]) == (2, 3.0, True)
    assert (config["depth"]["sources"], config["free_space"]["enabled"]) == (1, True)  # the rest of the group kept

    before = len(Client(server.url).sessions())
    assert cli.main(["stream", str(shelf_dir), *url, "--session", session_id, "--set", "sh_degree=0"]) == 2
    assert "--set" in capsys.readouterr().err
    assert cli.main(["stream", str(shelf_dir), *url, "--voxel-size", "0.01", "--set", "voxel_size=0.02"]) == 2
    assert "--voxel-size" in capsys.readouterr().err
    assert len(Client(server.url).sessions()) == before


@pytest.mark.realdata
def test_stream_by_default_lets_the_service_choose_the_voxel_size(server, shelf_dir, capsys):
    assert cli.build_parser().parse_args(["stream", "x", "--url", "http://x"]).voxel_size is None
    assert cli.main(["stream", str(shelf_dir), "--url", server.url, "--stride", "20", "--max-frames", "2",
                     "--scale", "0.25"]) == 0
    out, err = capsys.readouterr()
    stats = Client(server.url).session(out.strip()).stats()
    first = frame_arrays(load_tsdf_fusion(shelf_dir, max_frames=1)[0], 0.25)  # the frame as the CLI sent it
    depth, K = first["depth"], first["K"]
    assert stats["voxel_size"] == float(f"{6 * np.median(depth[depth > 0]) / ((K[0, 0] + K[1, 1]) / 2):.2g}")
    assert stats["chosen"]["voxel_size"] == "6 pixel footprints at the first frame's median depth"
    assert f"voxels of {stats['voxel_size'] * 1000:g} mm" in err and "structured_light noise model (default: " in err


@pytest.mark.parametrize("setting, message", [
    ("weighting", "NAME=VALUE"),
    ("colour_views=2", "colour_views: unknown setting"),
    ("research.weighting=average", "research.weighting: unknown setting"),  # evaluation only
    ("weighting=average", "weighting: unknown setting"),
    ("free_space=false", "free_space: a group"),
    ("free_space.margin=-1", "free_space.margin: input should be greater than or equal to 0"),
    ("sh_degree=1.5", "sh_degree: input should be a valid integer"),
    ("depth.completion=maybe", "depth.completion: input should be a valid boolean"),
    ("features.backend=cuda", "features.backend: input should be 'default' or 'client'"),
])
def test_set_refuses_what_the_settings_definition_refuses(setting, message, capsys):
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["stream", "x", "--voxel-size", "0.01", "--set", setting])
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("setting, parsed", [
    ("free_space.margin=3", ("free_space.margin", 3.0)),
    ("free_space.enabled=false", ("free_space.enabled", False)),
    ("max_voxels=null", ("max_voxels", None)),
    ("max_voxels=100000", ("max_voxels", 100000)),
    ("decoder.opacity_bias=-3", ("decoder.opacity_bias", -3.0)),
    ("features.backend=client", ("features.backend", "client")),
    (" sh_degree = 0", ("sh_degree", 0)),
])
def test_set_reads_values_as_the_fields_type(setting, parsed):
    args = cli.build_parser().parse_args(["stream", "x", "--voxel-size", "0.01", "--set", setting])
    assert args.settings == [parsed]


def test_demo_without_shared_data_fuses_a_generated_sample(tmp_path, monkeypatch, capsys):
    """The README's main job on a machine without ../shared/data: it generates a sample, starts its
    own service, streams it, and writes a render that resembles the input view and a PLY."""
    monkeypatch.setattr(demo, "SHARED_SHELF", tmp_path / "absent")
    out = tmp_path / "demo"
    assert cli.main(["demo", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "24 frames in" in printed and (out / "sample").is_dir()
    covered_psnr = float(printed.split("covered PSNR ")[1].split(" dB")[0])
    coverage = float(printed.split(" dB on the ")[1].split(" %")[0])
    # an input view of the generated scene at 2 cm voxels: measured 16.7 dB covered; the sky (no
    # depth, never seen) is the uncovered ~25 %
    assert covered_psnr > 15.0 and 65 < coverage < 85
    assert Image.open(out / "render.png").size == (320, 240)
    assert Image.open(out / "comparison.png").size == (640, 240)
    assert len(load_ply(out / "scene.ply")) > 1000


def test_demo_of_a_capture_given_lets_the_service_choose_the_voxel_size(tmp_path, capsys):
    """Any capture, room-scale too: not the shelf's 4 mm, but the voxel the service's rule fits to its depth."""
    capture = write_tsdf_fusion(synthetic_rgbd(num_frames=3, width=160, height=120), tmp_path / "capture")
    assert cli.main(["demo", str(capture), "--out", str(tmp_path / "demo")]) == 0
    printed = capsys.readouterr().out
    assert "at the voxel size the service chooses from the first frame" in printed
    assert float(printed.split(" voxels of ")[1].split(" mm")[0]) > 4 * 2


@pytest.mark.realdata
def test_demo_and_depth_take_the_intrinsics_a_capture_lacks_from_K(tmp_path, capsys):
    """The demo and the plane sweep read a capture as the stream does: a TUM capture without an
    intrinsics file is a usage error naming --K, and fused or swept with it."""
    capture = str(require_capture(DATA / "slambook_rgbd5"))
    K = ["--K", "518,519,325.5,253.5"]
    for argv in (["demo", capture, "--out", str(tmp_path / "demo")], ["depth", capture, "--out", str(tmp_path / "depth")]):
        assert cli.main(argv) == 2
        assert "error: --K: " in capsys.readouterr().err and not (tmp_path / argv[-1]).exists()
    assert cli.main(["demo", capture, "--out", str(tmp_path / "demo"), "--voxel-size", "0.02", *K]) == 0
    assert "5 frames in" in capsys.readouterr().out and (tmp_path / "demo" / "scene.ply").is_file()
    assert cli.main(["depth", capture, "--out", str(tmp_path / "depth"), "--max-frames", "2", *K]) == 0
    assert len(list((tmp_path / "depth").glob("*.depth.png"))) == 2
    assert "depth: 100%" in capsys.readouterr().err  # a bar over the frames: each sweep takes a second or more
    (tmp_path / "a-file").write_text("")
    assert cli.main(["depth", capture, "--out", str(tmp_path / "a-file" / "depth"), "--max-frames", "2", *K]) == 2
    assert "error: --out: cannot write" in capsys.readouterr().err


def test_demo_of_a_missing_capture_creates_nothing(tmp_path, capsys):
    assert cli.main(["demo", str(tmp_path / "no-such-capture"), "--out", str(tmp_path / "demo")]) == 1
    assert "no-such-capture" in capsys.readouterr().err and not (tmp_path / "demo").exists()


def test_a_service_started_with_a_relative_data_dir_keeps_its_data_under_the_callers_folder(tmp_path, monkeypatch):
    """`demo --out RELDIR` run elsewhere than the project: the service (a child in the project's folder)
    writes under RELDIR where it was run, not under the project."""
    monkeypatch.chdir(tmp_path)
    name = f"rel-{tmp_path.name}"
    service = start_service(free_port(), Path(name) / "data")
    try:
        assert (tmp_path / name / "data").is_dir()
        assert not (REPO / name).exists()
    finally:
        service.terminate()
        service.wait(timeout=60)


@pytest.mark.realdata
def test_depth_command_writes_pictures(shelf_dir, tmp_path, capsys):
    out = tmp_path / "depth"
    assert cli.main(["depth", str(shelf_dir), "--out", str(out), "--stride", "20", "--max-frames", "2"]) == 0
    assert "median AbsRel" in capsys.readouterr().out
    for name in ("frame-000015.depth.png", "frame-000015.uncertainty.png"):
        assert Image.open(out / name).size[0] >= 640
