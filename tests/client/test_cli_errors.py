"""The ``canonical`` CLI as a user runs it (a subprocess): one-line errors, Ctrl-C, resuming a stream."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from client.cli import build_parser
from client.cli.launch import free_port
from client.sdk import Client

REPO = Path(__file__).resolve().parents[2]


def canonical(*args: str, timeout: float = 120, env: dict | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(REPO / ".numba_cache"), **(env or {})}
    return subprocess.run([sys.executable, "-m", "client.cli", *args], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=timeout)


def assert_one_line_error(result: subprocess.CompletedProcess, code: int, *words: str) -> None:
    assert result.returncode == code, (result.stdout, result.stderr)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    for word in words:
        assert word in lines[0], lines[0]


BAD_ARGUMENTS = [
    ("no command", [], "required"),
    ("unknown command", ["frobnicate"], "invalid choice"),
    ("stream to a session and a voxel size", ["stream", "somewhere", "--session", "x", "--voxel-size", "0.01"],
     "not allowed with"),
    ("voxel size not a number", ["stream", "somewhere", "--voxel-size", "big"], "--voxel-size"),
    ("stride not an integer", ["stream", "somewhere", "--voxel-size", "0.01", "--stride", "1.5"], "--stride"),
    ("bad --set", ["stream", "somewhere", "--voxel-size", "0.01", "--set", "nonsense"], "NAME=VALUE"),
    ("render without output", ["render", "--session", "x", "--frame-like", "a:0"], "-o"),
    ("intrinsics not four numbers", ["render", "--session", "x", "--pose", "p", "--K", "1,two,3,4", "-o", "a.png"], "--K"),
    ("intrinsics of a stream", ["stream", "somewhere", "--K", "518,519,325"], "fx,fy,cx,cy"),
    ("unknown option", ["sessions", "--colour", "red"], "unrecognized"),
    ("negative wait for solved colours", ["export", "--session", "x", "-o", "a.ply", "--wait-solved", "-1"], "--wait-solved"),
    ("endless wait for solved colours", ["render", "--session", "x", "--frame-like", "a:0", "-o", "a.png",
                                         "--wait-solved", "inf"], "--wait-solved"),
    ("a log level uvicorn lacks", ["serve", "--log-level", "loud"], "--log-level"),
    ("an empty session id", ["view", "--session", ""], "--session"),
    ("no view to render", ["render", "--session", "x", "-o", "a.png"], "give the view(s)"),
    ("a size without a pose", ["render", "--session", "x", "--frame-like", "a:0", "--size", "64x48", "-o", "a.png"],
     "--size goes with --pose"),
    ("intrinsics without a size", ["render", "--session", "x", "--pose", "p", "--K", "1,2,3,4", "-o", "a.png"],
     "--K needs --size"),
    ("a pose without intrinsics", ["render", "--session", "x", "--pose", "p", "-o", "a.png"], "--pose and --trajectory need"),
    ("export to a text file", ["export", "--session", "x", "-o", "a.txt"], "-o: expected a .ply"),
    ("a mesh's level of detail", ["export", "--session", "x", "--mesh", "--max-gaussians", "9", "-o", "a.ply"],
     "--max-gaussians"),
    ("a dry run without prune", ["sessions", "--dry-run"], "--dry-run goes with --prune"),
    ("poses without poses", ["poses", "--session", "x"], "give a pose file, --remove"),
    ("settings of an existing session", ["stream", "somewhere", "--session", "x", "--set", "colour_solve.views=16"],
     "--set: settings belong to a new session"),
    ("the voxel size as a setting", ["stream", "somewhere", "--set", "voxel_size=0.01"], "--set: voxel_size"),
    ("a stride of 0", ["stream", "somewhere", "--stride", "0"], "argument --stride: expected a positive integer"),
    ("no frames", ["stream", "somewhere", "--max-frames", "0"], "argument --max-frames: expected a positive integer"),
    ("a scale of 0", ["stream", "somewhere", "--scale", "0"], "argument --scale: expected a positive number"),
    ("a depth scale of 0", ["stream", "somewhere", "--depth-scale", "0"], "argument --depth-scale: expected depth units per metre"),
    ("an overflowing depth scale of an evaluation", ["eval", "somewhere", "--out", "x", "--depth-scale", "1e-300"],
     "argument --depth-scale: expected depth units per metre"),
    ("a voxel size not a number", ["stream", "somewhere", "--voxel-size", "nan"], "argument --voxel-size: expected a positive"),
    ("an endless voxel", ["demo", "somewhere", "--voxel-size", "inf"], "argument --voxel-size: expected a positive"),
    ("intrinsics of the demo's own sample", ["demo", "--K", "518,519,325.5,253.5"], "--K: only for a DATASET given"),
    ("a depth scale of the demo's own sample", ["demo", "--depth-scale", "1000"], "--depth-scale: only for a DATASET"),
    ("intrinsics of a depth sweep", ["depth", "somewhere", "--out", "x", "--K", "518,519"], "argument --K: expected fx,fy"),
    ("no source views", ["depth", "somewhere", "--out", "x", "--sources", "0"], "argument --sources: expected a positive"),
    ("a background by name", ["render", "--session", "x", "--frame-like", "a:0", "--background", "red", "-o", "a.png"],
     "argument --background: expected r,g,b"),
    ("a background past 1", ["render", "--session", "x", "--frame-like", "a:0", "--background", "1,2,0", "-o", "a.png"],
     "argument --background: expected r,g,b"),
    ("an interval not a number", ["watch", "--session", "x", "--every", "nan"], "argument --every: expected a number"),
]


@pytest.mark.parametrize("argv, word", [c[1:] for c in BAD_ARGUMENTS], ids=[c[0] for c in BAD_ARGUMENTS])
def test_bad_arguments_are_one_line(argv, word):
    url = ["--url", f"http://127.0.0.1:{free_port()}"] if argv and argv[0] not in ("serve", "frobnicate", "demo", "depth") \
        else []
    assert_one_line_error(canonical(*argv, *url), 2, "error: ", word)


@pytest.mark.parametrize("output, words", [
    ("a.png", ["-o: 2 views need a pattern with {i}"]),
    ("a_{j}.png", ["-o: expected a pattern with {i}"]),
    ("a_{{i}}.png", ["names one file for several views"]),
], ids=["one file", "no {i}", "one name"])
def test_an_output_that_cannot_hold_the_views_is_a_usage_error(shelf_dir, tmp_path, output, words):
    result = canonical("render", "--url", f"http://127.0.0.1:{free_port()}", "--session", "x", "--frame-like",
                       f"{shelf_dir}:0", "--frame-like", f"{shelf_dir}:1", "-o", str(tmp_path / output))
    assert_one_line_error(result, 2, "error: ", *words)


@pytest.mark.parametrize("option", ["--trajectory", "--pose"])
def test_a_pose_file_without_poses_is_one_line_naming_the_option(tmp_path, option):
    (tmp_path / "comments.txt").write_text("# timestamp tx ty tz qx qy qz qw\n\n  # no pose yet\n")
    for path in (str(tmp_path / "comments.txt"), "/dev/null"):
        result = canonical("render", "--url", f"http://127.0.0.1:{free_port()}", "--session", "x", option, path,
                           "--K", "8,8,4,4", "--size", "8x8", "-o", str(tmp_path / "v_{i}.png"))
        assert_one_line_error(result, 1, f"{option}: no poses in {path}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["comments.txt"]


def test_log_levels_are_read_in_any_case():
    assert build_parser().parse_args(["serve", "--log-level", "WARNING"]).log_level == "warning"


def test_unreachable_server_is_one_line():
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    assert_one_line_error(canonical("sessions", "--url", url), 1, f"--url: cannot reach the service at {url}: ", "refused")
    assert_one_line_error(canonical("export", "--url", url, "--session", "x", "-o", "a.ply"), 1, "cannot reach")


@pytest.mark.parametrize("argv, code, words", [
    (["sessions", "--url", "http://256.1.1.1:1"], 2, ["--url", "256.1.1.1"]),
    (["sessions", "--url", "nonsense"], 2, ["--url", "nonsense"]),
    (["view", "--url", "ftp://127.0.0.1:1", "--session", "x"], 2, ["--url", "ftp://"]),
], ids=["invalid address", "no scheme", "not http"])
def test_an_unusable_url_is_one_line_naming_the_option(argv, code, words):
    assert_one_line_error(canonical(*argv), code, *words)


def test_stream_to_an_unusable_url_is_one_line(shelf_dir):
    assert_one_line_error(canonical("stream", str(shelf_dir), "--url", "http://256.1.1.1:1", "--voxel-size", "0.02"),
                          2, "--url", "256.1.1.1")


@pytest.mark.parametrize("suffix, code, words", [
    (":999", 2, ["--frame-like", "has 50 frames", "999"]),
    (":-1", 2, ["--frame-like", "has 50 frames", "-1"]),
    ("", 2, ["--frame-like", "DATASET:INDEX"]),
    ("/no-such-capture:0", 1, ["--frame-like", "no-such-capture"]),
], ids=["past the end", "negative", "no index", "missing capture"])
def test_a_bad_frame_like_is_one_line_before_any_request(shelf_dir, tmp_path, suffix, code, words):
    url = f"http://127.0.0.1:{free_port()}"  # nothing listens there: a request would say "cannot reach"
    result = canonical("render", "--url", url, "--session", "x", "--frame-like", f"{shelf_dir}{suffix}",
                       "-o", str(tmp_path / "a.png"))
    assert_one_line_error(result, code, *words)
    assert not (tmp_path / "a.png").exists()


@pytest.mark.parametrize("argv, env, words", [
    (["--port", "99999"], {}, ["--port", "65535", "got 99999"]),
    (["--threads", "0"], {}, ["--threads", "greater than 0", "got 0"]),
    ([], {"CANONICAL_QUEUE_LIMIT": "0"}, ["CANONICAL_QUEUE_LIMIT", "got 0"]),
    # two settings that do not fit together: the one to change named, the token of the others never shown
    ([], {"CANONICAL_API_TOKEN": "s3cr3t-token", "CANONICAL_MAX_BODY_BYTES": "2000000000"},
     ["CANONICAL_MAX_INFLIGHT_BODY_BYTES", "at least max_body_bytes (2000000000)"]),
    # a blank token would be a check anyone passes with "Authorization: Bearer "
    ([], {"CANONICAL_API_TOKEN": " "}, ["CANONICAL_API_TOKEN: is empty: unset it"]),
    # a host no address of this machine has: that setting named, not the port
    (["--host", "host.invalid"], {}, ["--host: cannot listen on host.invalid"]),
    ([], {"CANONICAL_HOST": "192.0.2.1"}, ["CANONICAL_HOST: cannot listen on 192.0.2.1"]),
], ids=["port", "threads", "from the environment", "two that do not fit", "a blank token", "an unknown host",
        "a host of another machine"])
def test_a_bad_serve_setting_is_one_line_naming_it_and_creates_nothing(tmp_path, argv, env, words):
    data = tmp_path / "data"
    result = canonical("serve", "--data-dir", str(data), *argv, env=env)
    assert_one_line_error(result, 2, *words)
    assert "s3cr3t" not in result.stderr + result.stdout and not data.exists()


def test_a_data_dir_that_cannot_be_created_is_one_line():
    result = canonical("serve", "--data-dir", "/proc/nope", "--port", str(free_port()))
    assert_one_line_error(result, 1, "--data-dir: cannot create /proc/nope", "No such file or directory")


def test_a_second_server_on_a_locked_data_dir_says_so_in_one_line(server):
    result = canonical("serve", "--data-dir", str(server.data_dir), "--port", str(free_port()))
    assert_one_line_error(result, 1, "--data-dir", "in use by another server", f"pid {server.proc.pid}")


def test_repair_of_a_missing_data_dir_says_so_and_creates_nothing(tmp_path):
    typo = tmp_path / "typo"
    assert_one_line_error(canonical("repair", "--data-dir", str(typo)), 1, "--data-dir", str(typo), "does not exist")
    assert not typo.exists()
    typo.mkdir()  # a folder, but no service's data directory: nothing is created in it either
    assert_one_line_error(canonical("repair", "--data-dir", str(typo)), 1, "--data-dir", "not a data directory")
    assert list(typo.iterdir()) == []


def test_bad_values_after_parsing_are_one_line(server, tmp_path):
    assert_one_line_error(canonical("render", "--url", server.url, "--session", "x", "--pose", str(tmp_path / "missing.txt"),
                                     "--K", "1,2,3,4", "--width", "8", "--height", "8", "-o", str(tmp_path / "a.png")), 1, "missing.txt")
    assert_one_line_error(canonical("stream", str(tmp_path / "no-such-dataset"), "--url", server.url, "--voxel-size", "0.01"),
                          1, "no-such-dataset")
    assert_one_line_error(canonical("depth", str(tmp_path / "no-such-dataset"), "--out", str(tmp_path / "d")), 1,
                          "no-such-dataset: not a folder")
    assert_one_line_error(canonical("export", "--url", server.url, "--session", "no-such", "-o", str(tmp_path / "a.ply")),
                          1, "404")


def test_stream_resumes_after_the_frames_the_session_has(server, shelf_dir):
    common = [str(shelf_dir), "--url", server.url, "--stride", "10", "--scale", "0.25"]
    first = canonical("stream", *common, "--voxel-size", "0.02", "--max-frames", "2")
    assert first.returncode == 0, first.stderr
    session_id = first.stdout.strip()
    again = canonical("stream", *common, "--session", session_id, "--max-frames", "4")
    assert again.returncode == 0, again.stderr
    assert "resuming after its 2 frames" in again.stderr and "2 frames in" in again.stderr
    stats = httpx.get(f"{server.url}/v1/sessions/{session_id}").json()
    assert stats["frames"] == 4  # frames 0-1 once, then 2-3: none sent twice


def test_stream_resumes_past_the_frames_the_session_holds_after_one_was_removed(server, shelf_dir):
    common = [str(shelf_dir), "--url", server.url, "--stride", "10", "--scale", "0.25"]
    first = canonical("stream", *common, "--voxel-size", "0.02", "--max-frames", "3")
    assert first.returncode == 0, first.stderr
    session_id = first.stdout.strip()
    with Client(server.url) as client:
        assert client.session(session_id).remove_frame("frame-000035")["frames"] == 2  # the capture's frame 1
    again = canonical("stream", *common, "--session", session_id, "--max-frames", "5", timeout=60)
    assert again.returncode == 0, again.stderr
    assert "resuming after its 2 frames" in again.stderr and "1 frames of realsense_shelf from frame 2 on were in the " \
        "session already" in again.stderr and "2 frames in" in again.stderr
    # frames 0 and 2 held, 3 and 4 new; the removed frame 1 stays removed
    assert httpx.get(f"{server.url}/v1/sessions/{session_id}").json()["frames"] == 4


def frames_of(server, session_id: str) -> int:
    """The session's frame count from the session list, which runs no job: a stats request would queue behind
    the stream's fold and get 429 from this one-job server."""
    sessions = httpx.get(f"{server.url}/v1/sessions").json()["sessions"]
    return next(s["frames"] for s in sessions if s["id"] == session_id)


def test_ctrl_c_stops_cleanly_with_a_summary(server, shelf_dir):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(REPO / ".numba_cache")}
    # SIGINT back to its default in the child: a test run started in the background of a shell
    # without job control inherits it ignored, and the stream would never see the interrupt
    proc = subprocess.Popen([sys.executable, "-m", "client.cli", "stream", str(shelf_dir), "--url", server.url,
                             "--voxel-size", "0.02", "--scale", "0.25"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        session_id = proc.stdout.readline().strip()  # printed once the session holds its first frame
        deadline = time.monotonic() + 120
        while frames_of(server, session_id) < 1:
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    frames = frames_of(server, session_id)
    assert out == "" and "interrupted: " in err and f"session {session_id}: {frames} frames" in err
    assert f"--session {session_id}" in err and 1 <= frames < 50


def test_a_port_taken_or_a_data_dir_that_cannot_be_made_is_one_line_before_anything_starts(tmp_path):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for cluster in ([], ["--cluster"]):
            result = canonical("serve", *cluster, "--port", str(port), "--data-dir", str(tmp_path / "data"))
            assert_one_line_error(result, 2, "--port", f"127.0.0.1:{port}")
    # the cluster's data directory is made before Ray starts
    result = canonical("serve", "--cluster", "--port", str(free_port()), "--data-dir", "/proc/no-such/data")
    assert_one_line_error(result, 1, "--data-dir: cannot create", "/proc/no-such")


@pytest.mark.parametrize("address, env, words", [
    (["--address", "127.0.0.1:{port}"], {}, ["--address: no Ray cluster answers at 127.0.0.1:{port}", "refused"]),
    (["--address", "ray://127.0.0.1:{port}"], {}, ["--address: no Ray cluster answers at 127.0.0.1:{port}"]),
    ([], {"RAY_ADDRESS": "127.0.0.1:{port}"}, ["RAY_ADDRESS: no Ray cluster answers at 127.0.0.1:{port}"]),
    (["--address", "127.0.0.1:port"], {}, ["--address: '127.0.0.1:port' is not HOST:PORT"]),
], ids=["a head's address", "a Ray Client address", "from the environment", "no port number"])
def test_a_ray_cluster_that_does_not_answer_is_one_line_at_once(tmp_path, address, env, words):
    port = free_port()  # nothing listens there
    result = canonical("serve", "--cluster", "--port", str(free_port()), "--data-dir", str(tmp_path / "data"),
                       *(a.format(port=port) for a in address), env={k: v.format(port=port) for k, v in env.items()},
                       timeout=60)
    assert_one_line_error(result, 2, *(w.format(port=port) for w in words))


def test_a_variable_that_is_no_setting_is_warned_of_naming_the_setting_it_resembles(monkeypatch, capsys):
    """CANONICAL_QUEUE_LIMT=3 would otherwise leave the queue limit at its default without a word."""
    from client.cli.serve import serve_settings

    monkeypatch.setenv("CANONICAL_QUEUE_LIMT", "3")
    monkeypatch.setenv("CANONICAL_OWNERS", "2")  # the cluster's: no warning without --cluster either
    settings = serve_settings(build_parser().parse_args(["serve"]))
    assert settings.queue_limit == 8
    warned = capsys.readouterr().err.splitlines()
    assert ("warning: CANONICAL_QUEUE_LIMT is not a setting of the service (did you mean CANONICAL_QUEUE_LIMIT?); "
            "ignored") in warned and not any("CANONICAL_OWNERS" in line for line in warned)
