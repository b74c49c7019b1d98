"""The colour solve in the background of a real service: a stream that pauses is shown in the
library's solved colours, a frame sent while a solve runs is taken without waiting for it, and a
restarted service (kill -9) shows the same solved colours again."""

from __future__ import annotations

import time

import httpx
import numpy as np
import pytest

from canonical_core import SceneConfig
from canonical_core.camera import Camera
from canonical_core.rendering import render
from canonical_core.scene import Scene
from client.sdk import Client
from server import wire
from server.solves import QUIET_S

from .harness import SOLVE_WAIT_S, VOXEL, ServerProcess, msgpack_frame, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]



def library_rgb(frames: list[dict], view: tuple) -> np.ndarray:  # [H, W, 3] uint8
    """The library's render of ``frames`` folded with the defaults and their colours solved: what the
    service must show once it has solved them (the same wire conversion, the same render call)."""
    scene = Scene(SceneConfig(voxel_size=VOXEL))
    for kwargs in frames:
        scene.fold(wire.frame_from_message(msgpack_frame(kwargs)))
    assert scene.solve_colours()
    out = render(scene.gaussians(colours="last", features=False), Camera(*view), ("rgb",), colour="normalised")
    return wire.to_uint8(out.rgb.numpy())


def view_of(kwargs: dict) -> tuple:
    h, w = kwargs["rgb"].shape[:2]
    return kwargs["K"], kwargs["c2w"], w, h


def solved(session, frames: int) -> bool:
    return session.stats()["colours_solved_frames"] == frames


def test_a_paused_stream_shows_the_librarys_solved_colours_and_a_restart_keeps_them(tmp_path, frames):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_frames=3, snapshot_every_seconds=3600)
    streamed, view = frames[:5], view_of(frames[2])
    expected = library_rgb(streamed, view)
    try:
        client = Client(proc.start().url)
        session = client.create_session(voxel_size=VOXEL)  # the defaults: the colour solve on
        assert session.stats()["config"]["colour_solve"]["views"] == 16
        for kwargs in streamed:
            session.add_frame(**kwargs)
        # nobody renders: the pause alone gets the colours solved, for the state after the last frame
        assert wait_for(lambda: solved(session, len(streamed)), SOLVE_WAIT_S), session.stats()
        shown = session.render(*view)["rgb"]
        assert np.array_equal(shown, expected)
        assert np.array_equal(session.render(*view)["rgb"], shown)  # deterministic: the same pixels again
        digest = session.digest()["sha256"]
        proc.kill9()

        client = Client(proc.start().url)
        session = client.session(session.id)
        assert session.digest()["sha256"] == digest  # solving never touched the fused state
        # nobody renders: the service solves its restored sessions' colours again as it starts
        assert session.wait_for_colours(SOLVE_WAIT_S)["colours_solved_frames"] == len(streamed), session.stats()
        assert np.array_equal(session.render(*view)["rgb"], expected)

        # nobody renders: a correction's scene gets its colours solved, answered at once or in the background
        session.remove_frame(streamed[4]["frame_id"])
        assert session.wait_for_colours(SOLVE_WAIT_S)["colours_solved_frames"] == 4, session.stats()
        status = session.update_poses({}, remove=[streamed[3]["frame_id"]], wait=False)
        assert wait_for(lambda: session.correction(status["correction_id"])["state"] == "done", SOLVE_WAIT_S)
        assert session.wait_for_colours(SOLVE_WAIT_S)["colours_solved_frames"] == 3, session.stats()
        assert np.array_equal(session.render(*view)["rgb"], library_rgb(streamed[:3], view))
    finally:
        proc.kill9()


def gauge(url: str, name: str) -> float:
    text = httpx.get(f"{url}/metrics").text
    return float(next(line.split()[1] for line in text.splitlines() if line.startswith(name + " ")))


def test_a_frame_sent_while_a_solve_runs_is_taken_at_once_and_stops_the_solve(tmp_path, frames):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", snapshot_every_seconds=3600)
    try:
        client = Client(proc.start().url)
        # full-size kept views at a finer voxel: a solve of seconds against a fold's fraction of one
        session = client.create_session(voxel_size=VOXEL / 2, colour_solve={"scale": 1.0})
        for kwargs in frames[:5]:
            session.add_frame(**kwargs)
        # the pause after the fifth frame started a solve; a frame arrives while it runs: the solve
        # gives way to it at its next step and lands nothing, and the frame is taken. A solve may still
        # end first by chance (on a quiet machine it takes about a second): then the next frame tries
        # again. A solve that went on would never count as stopped, and would land a solution of the
        # state before the frame.
        stopped_by = None
        for k in range(5, len(frames)):
            assert wait_for(lambda: gauge(proc.url, "canonical_colour_solves_running") == 1, SOLVE_WAIT_S)
            time.sleep(2 * QUIET_S)  # past the solve's wait for a pause: solving (a frame before would only cancel it)
            stopped, done = session.stats()["colour_solves_stopped"], gauge(proc.url, "canonical_colour_solves_done_total")
            assert session.add_frame(**frames[k])["frame_index"] == k
            assert wait_for(lambda: gauge(proc.url, "canonical_colour_solves_done_total") > done, SOLVE_WAIT_S)
            if session.stats()["colour_solves_stopped"] == stopped + 1:
                stopped_by = k
                break
        assert stopped_by is not None, session.stats()
        shown = session.stats()["colours_solved_frames"]
        assert shown is None or 5 <= shown <= stopped_by  # of a state before the frame, if any
        assert wait_for(lambda: solved(session, k + 1), SOLVE_WAIT_S), session.stats()  # the pause gets them solved
    finally:
        proc.kill9()
