"""The ``canonical`` CLI in scripts, as a user runs it (a subprocess) against a real service: results
alone on stdout (ids, paths, JSON), no session left behind by a stream that fails at its start, the
session list, many views in one render call, captures with missing images, frames over the limit."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import httpx
import numpy as np
import pytest
from PIL import Image

from canonical_core.datasets import load_tsdf_fusion
from client.cli.render import frame_like_camera
from client.cli.sessions import watch_line
from client.sdk import Client
from tests.client.test_cli_errors import REPO, assert_one_line_error, canonical
from tests.client.test_cli_poses import matrix_to_tum
from tests.datasets.test_datasets_transforms_json import _write_capture
from tests.server.harness import colours_solved

SESSION_ID = re.compile(r"^[0-9a-f]{32}$")
SMALL = ["--stride", "20", "--max-frames", "2", "--scale", "0.25", "--voxel-size", "0.02"]


def session_ids(server) -> set[str]:
    return {s["id"] for s in httpx.get(f"{server.url}/v1/sessions").json()["sessions"]}


def test_stream_prints_the_session_id_alone_on_stdout(server, shelf_dir, tmp_path):
    streamed = canonical("stream", str(shelf_dir), "--url", server.url, *SMALL)
    assert streamed.returncode == 0, streamed.stderr
    session_id = streamed.stdout.strip()  # what S=$(canonical stream ...) captures
    assert SESSION_ID.match(session_id) and streamed.stdout == session_id + "\n"
    assert "2 frames in" in streamed.stderr and f"session {session_id}: 2 frames" in streamed.stderr

    resumed = canonical("stream", str(shelf_dir), "--url", server.url, "--session", session_id, "--stride", "20",
                        "--max-frames", "3", "--scale", "0.25", "--json")
    assert resumed.returncode == 0, resumed.stderr
    stats = json.loads(resumed.stdout)  # the final stats, nothing else on stdout
    assert (stats["id"], stats["frames"], stats["sent"], stats["interrupted"]) == (session_id, 3, 1, False)
    assert stats["gaussians"] > 0 and stats["config"]["voxel_size"] == 0.02

    exported = canonical("export", "--url", server.url, "--session", session_id, "-o", str(tmp_path / "scene.ply"))
    assert exported.returncode == 0 and exported.stdout == f"{tmp_path / 'scene.ply'}\n", exported.stderr


def test_export_and_render_straight_after_a_stream_show_its_solved_colours(server, shelf_dir, tmp_path):
    # full-size frames: their solve takes longer than the commands below take to start
    session_id = canonical("stream", str(shelf_dir), "--url", server.url, "--stride", "10", "--max-frames", "5",
                           "--voxel-size", "0.006").stdout.strip()
    # at once, as a script does: each waits (by default) for the colours the service solves once the stream pauses
    exported = canonical("export", "--url", server.url, "--session", session_id, "-o", str(tmp_path / "cli.ply"))
    view = f"{shelf_dir}:20"
    rendered = canonical("render", "--url", server.url, "--session", session_id, "--frame-like", view,
                         "-o", str(tmp_path / "cli.png"))
    assert exported.returncode == 0 and rendered.returncode == 0, (exported.stderr, rendered.stderr)
    with Client(server.url) as client:
        session = client.session(session_id)
        stats = session.wait_for_colours(0)  # no wait: as the service holds it now
        assert stats["colours_solved_frames"] == stats["frames"] == 5
        assert (tmp_path / "cli.ply").read_bytes() == session.export_ply(tmp_path / "solved.ply").read_bytes()
        assert (tmp_path / "cli.png").read_bytes() == session.render_png(*frame_like_camera(view))


def test_a_stream_whose_first_frame_is_refused_leaves_no_session(server, shelf_dir):
    before = session_ids(server)
    # a scene of one voxel cannot take the first frame: the service refuses it (409 capacity)
    refused = canonical("stream", str(shelf_dir), "--url", server.url, *SMALL, "--set", "max_voxels=1")
    assert refused.returncode == 1 and "409" in refused.stderr and refused.stdout == ""
    assert session_ids(server) == before


def test_sessions_lists_size_memory_disk_and_age(server, shelf_dir):
    session_id = canonical("stream", str(shelf_dir), "--url", server.url, *SMALL).stdout.strip()
    # the session's background colour solve lands once the stream is idle and adds its solution to
    # the memory: the listing and the stats below must read the same state
    with Client(server.url) as client:
        assert colours_solved(client.session(session_id))
    table = canonical("sessions", "--url", server.url)
    assert table.returncode == 0, table.stderr
    header, *rows = table.stdout.splitlines()
    assert header.split() == ["id", "voxel", "frames", "memory", "disk", "age", "state"]
    row = next(r for r in rows if r.startswith(session_id))
    assert re.fullmatch(rf"{session_id}\s+20 mm\s+2\s+[\d.]+ (KiB|MiB)\s+[\d.]+ (KiB|MiB)\s+\d+ s\s+ok", row), row

    listed = canonical("sessions", "--url", server.url, "--json")
    entry = next(s for s in json.loads(listed.stdout) if s["id"] == session_id)
    stats = httpx.get(f"{server.url}/v1/sessions/{session_id}").json()
    assert entry["voxel_size"] == 0.02 and entry["frames"] == 2
    assert entry["memory_bytes"] == stats["memory_bytes"] > 0 and entry["disk_bytes"] == stats["disk_bytes"] > 0
    assert 0 <= entry["age_s"] < 600 and entry["created"] == stats["created"]


def test_render_draws_many_views_in_one_call(server, shelf_dir, tmp_path):
    session_id = canonical("stream", str(shelf_dir), "--url", server.url, *SMALL).stdout.strip()
    url = ["--url", server.url, "--session", session_id]
    with Client(server.url) as client:  # renders below compare one state: the one after its background solve
        assert colours_solved(client.session(session_id))

    liked = canonical("render", *url, "--frame-like", f"{shelf_dir}:0", "--frame-like", f"{shelf_dir}:20",
                      "-o", str(tmp_path / "like_{i}.png"))
    assert liked.returncode == 0, liked.stderr
    assert liked.stdout.splitlines() == [str(tmp_path / "like_0.png"), str(tmp_path / "like_1.png")]
    assert all(Image.open(p).size == (640, 480) for p in liked.stdout.splitlines())

    shelf = load_tsdf_fusion(shelf_dir)
    poses = [shelf[k].camera.c2w64() for k in (0, 10, 20)]
    trajectory = tmp_path / "trajectory.txt"  # TUM: timestamp tx ty tz qx qy qz qw
    trajectory.write_text("# timestamp tx ty tz qx qy qz qw\n"
                          + "".join(f"{t}.5 " + " ".join(repr(float(x)) for x in matrix_to_tum(T)) + "\n" for t, T in enumerate(poses)))
    walked = canonical("render", *url, "--trajectory", str(trajectory), "--K", "150,150,79.5,59.5", "--size", "160x120",
                       "-o", str(tmp_path / "walk") + "/")
    assert walked.returncode == 0, walked.stderr
    paths = walked.stdout.splitlines()
    assert paths == [str(tmp_path / "walk" / f"view_{i:04d}.png") for i in range(3)]
    assert all(Image.open(p).size == (160, 120) for p in paths)

    # a TUM pose line in --pose, with the intrinsics and size of a --frame-like frame: the same view
    # as that frame's own camera (the quaternion read as the loaders read it)
    pose = tmp_path / "pose.txt"
    pose.write_text(" ".join(repr(float(x)) for x in matrix_to_tum(poses[2])) + "\n")
    posed = canonical("render", *url, "--pose", str(pose), "--frame-like", f"{shelf_dir}:0", "-o", str(tmp_path / "posed.png"))
    assert posed.returncode == 0 and posed.stdout == str(tmp_path / "posed.png") + "\n", posed.stderr
    a, b = (np.asarray(Image.open(p), np.int16) for p in (tmp_path / "posed.png", tmp_path / "like_1.png"))
    assert np.abs(a - b).max() <= 2

    several = canonical("render", *url, "--trajectory", str(trajectory), "--K", "150,150,79.5,59.5", "--size", "160x120",
                        "-o", str(tmp_path / "one.png"))
    assert several.returncode == 2 and "error: -o: 3 views need a pattern with {i}" in several.stderr
    assert not (tmp_path / "one.png").exists()


@pytest.fixture
def partial_capture(shelf_dir, tmp_path):
    """A transforms.json that lists 4 frames, one of whose images was never copied."""
    frames = _write_capture(load_tsdf_fusion(shelf_dir), shelf_dir, tmp_path / "ns", count=4)
    (tmp_path / "ns" / "images" / f"{frames[2].frame_id}.png").unlink()
    return tmp_path / "ns"


def test_stream_skips_listed_frames_whose_images_are_missing(server, partial_capture):
    streamed = canonical("stream", str(partial_capture), "--url", server.url, "--scale", "0.25", "--voxel-size", "0.02")
    assert streamed.returncode == 0, streamed.stderr
    warned = [line for line in streamed.stderr.splitlines() if line.startswith("warning: ")]
    assert len(warned) == 1 and "skipped 1 of 4 listed frames" in warned[0] and "--strict" not in streamed.stdout
    assert "--strict refuses such a capture" in warned[0] and "strict=True" not in warned[0]  # the CLI's option
    stats = httpx.get(f"{server.url}/v1/sessions/{streamed.stdout.strip()}").json()
    assert stats["frames"] == 3

    before = session_ids(server)
    strict = canonical("stream", str(partial_capture), "--url", server.url, "--scale", "0.25", "--voxel-size", "0.02",
                       "--strict")
    assert strict.returncode == 1 and "file not found" in strict.stderr and strict.stdout == ""
    assert session_ids(server) == before  # refused before any session was made


def test_stream_downscales_frames_without_depth_to_the_services_limit(server, partial_capture):
    """A phone capture: 1920x1080 colour, no depth, over the service's 1.3 MP limit for such frames.
    The stream sends the frames downscaled to the limit and says so once."""
    meta = json.loads((partial_capture / "transforms.json").read_text())
    meta["frames"] = [f for f in meta["frames"] if (partial_capture / f["file_path"]).is_file()][:2]
    for f in meta["frames"]:
        del f["depth_file_path"]
        image = partial_capture / f["file_path"]
        Image.open(image).resize((1920, 1080), Image.BILINEAR).save(image)
    sx, sy = 1920 / meta["w"], 1080 / meta["h"]
    meta.update(w=1920, h=1080, fl_x=meta["fl_x"] * sx, fl_y=meta["fl_y"] * sy, cx=meta["cx"] * sx, cy=meta["cy"] * sy)
    (partial_capture / "transforms.json").write_text(json.dumps(meta))
    shutil.rmtree(partial_capture / "depth")

    streamed = canonical("stream", str(partial_capture), "--url", server.url, "--voxel-size", "0.02")
    assert streamed.returncode == 0, streamed.stderr
    told = [line for line in streamed.stderr.splitlines() if "downscaled to 1526x858" in line]
    assert len(told) == 1 and "1920x1080" in told[0]
    cameras = httpx.get(f"{server.url}/v1/sessions/{streamed.stdout.strip()}/cameras").json()["cameras"]
    assert [(c["width"], c["height"]) for c in cameras] == [(1526, 858)] * 2


def test_watch_prints_each_fold_as_it_comes_and_ends_when_the_session_is_deleted(server, frames):
    with Client(server.url) as client:
        session = client.create_session(voxel_size=0.02)
        watch = subprocess.Popen([sys.executable, "-m", "client.cli", "watch", "--url", server.url, "--session", session.id,
                                  "--every", "0", "--json"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True)
        try:
            assert json.loads(watch.stdout.readline()) == {"event": "state", "frames": 0, "voxels": 0, "label_dim": 0}
            reports = [session.add_frame(**kwargs) for kwargs in frames[:2]]
            session.delete()
            out, err = watch.communicate(timeout=60)
        finally:
            watch.kill()
    assert watch.returncode == 0, err
    events = [json.loads(line) for line in out.splitlines()]
    assert [e["event"] for e in events] == ["fold", "fold", "deleted"]
    assert [e["report"] for e in events[:2]] == reports and events[1]["frames"] == 2


def test_watch_of_a_service_that_dies_ends_with_an_error_not_as_a_deleted_session(tmp_path):
    """Exit 0 means the session was deleted: a service killed under the stream is an error the user
    is told of (a script watching for the end would otherwise take a crash for it)."""
    from tests.server.harness import ServerProcess

    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", warm_up="false").start()
    try:
        with Client(proc.url) as client:
            session = client.create_session(voxel_size=0.02)
        watch = subprocess.Popen([sys.executable, "-m", "client.cli", "watch", "--url", proc.url, "--session", session.id],
                                 cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert "waiting for folds" in watch.stdout.readline()
            proc.kill9()
            _, err = watch.communicate(timeout=60)
        finally:
            watch.kill()
    finally:
        proc.kill9()
    assert watch.returncode == 1 and "the service ended the stream" in err, err


def test_watch_lines_say_the_fold_its_counts_and_the_latest_warning():
    fold = {"frames": 7, "voxels": 1200, "report": {"frame_index": 6, "warnings": []}}
    assert watch_line("fold", fold) == "frame 6: 7 frames, 1200 voxels"
    batched = {**fold, "folds": 3, "warned": {"frame_index": 5, "warnings": ["depth under the working range"]}}
    assert watch_line("fold", batched) == "frame 6: 7 frames, 1200 voxels (3 folds); frame 5: depth under the working range"
    assert watch_line("state", {"frames": 0, "voxels": 0}) == "0 frames, 0 voxels: waiting for folds"
    assert watch_line("fold", {**fold, "frames": 1}) == "frame 6: 1 frame, 1200 voxels"
    assert watch_line("deleted", {"id": "abc"}) == "session abc deleted"


def test_watch_refuses_a_negative_interval_and_an_unknown_session(server):
    assert_one_line_error(canonical("watch", "--url", server.url, "--session", "nope", "--every", "-1"), 2, "--every")
    assert_one_line_error(canonical("watch", "--url", server.url, "--session", "nope"), 1, "session")
