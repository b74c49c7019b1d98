"""A session created without voxel_size over a real service: its first frame with depth chooses the voxel
size (6 pixel footprints at its median depth) and the sensor family, the session's GET and fold
reports say so, meta.json records it, and a graceful restart, a kill -9 and the removal of that
frame keep it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from client.sdk import CanonicalError, Client

from .harness import ServerProcess

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


def rule(kwargs: dict) -> float:
    """The voxel size the service should choose from this frame, by the rule's words (not its code)."""
    depth, K = kwargs["depth"], kwargs["K"]
    return float(f"{6 * float(np.median(depth[depth > 0])) / ((K[0, 0] + K[1, 1]) / 2):.2g}")


def test_the_first_frame_chooses_the_voxel_size_and_restarts_keep_it(tmp_path, frames):
    data = tmp_path / "data"
    proc = ServerProcess(data, tmp_path / "server.log", snapshot_every_frames=3, snapshot_every_seconds=3600)
    try:
        proc.start()
        client = Client(proc.url)
        session = client.create_session()  # no voxel_size: the service chooses it
        stats = session.stats()
        assert (stats["voxel_size"], stats["sensor"], stats["chosen"]) == (None, "auto", {})
        assert stats["config"]["voxel_size"] is None and stats["config"]["sensor"]["family"] == "auto"

        # a first frame without depth cannot choose it: refused naming voxel_size, nothing changes
        with pytest.raises(CanonicalError) as refused:
            session.add_frame(**{**frames[0], "depth": None, "frame_id": "no-depth"})
        assert (refused.value.status, refused.value.field) == (422, "voxel_size")
        assert session.stats()["frames"] == 0 and session.stats()["voxel_size"] is None

        report = session.add_frame(**frames[0])
        assert report["sensor"] == "structured_light" and report["sensor_chosen"].startswith("default: ")
        chosen = session.stats()
        assert chosen["voxel_size"] == rule(frames[0]) and chosen["sensor"] == "structured_light"
        assert chosen["chosen"]["voxel_size"] == "6 pixel footprints at the first frame's median depth"
        assert chosen["config"]["sensor"]["sigma0"] is not None  # the family's values, fixed from now on
        meta = json.loads((data / "sessions" / session.id / "meta.json").read_text())
        assert meta["config"] == chosen["config"] and meta["chosen"] == chosen["chosen"]
        assert [s["voxel_size"] for s in client.sessions() if s["id"] == session.id] == [rule(frames[0])]

        # a later frame changes nothing: the session equals one given that size
        for kwargs in frames[1:2]:
            session.add_frame(**kwargs)
        assert session.stats()["voxel_size"] == rule(frames[0])
        given = client.create_session(voxel_size=rule(frames[0]))
        for kwargs in frames[:2]:
            given.add_frame(**kwargs)
        assert given.digest()["sha256"] == session.digest()["sha256"]

        proc.kill9()  # 2 frames in the log, no snapshot yet: meta.json holds the choice
        proc.start()
        session = Client(proc.url).session(session.id)
        assert {k: session.stats()[k] for k in ("voxel_size", "sensor", "chosen", "config", "frames")} == \
            {**{k: chosen[k] for k in ("voxel_size", "sensor", "chosen", "config")}, "frames": 2}
        again = session.add_frame(**frames[0])  # a retry of the first frame, re-folded from the log at the restart
        assert {**again, "ms": 0} == {**report, "ms": 0}  # its first report (the fold time aside)
        for kwargs in frames[2:5]:  # a snapshot at 3 frames
            session.add_frame(**kwargs)
        before = session.digest()
        proc.stop()
        assert (data / "sessions" / session.id / "scene.snap").exists()
        proc.start()
        session = Client(proc.url).session(session.id)
        assert session.digest() == before
        assert (session.stats()["voxel_size"], session.stats()["chosen"]) == (chosen["voxel_size"], chosen["chosen"])

        session.remove_frame(frames[0]["frame_id"])  # the frame that chose: the choice stays for the session's life
        assert {k: session.stats()[k] for k in ("voxel_size", "chosen", "config", "frames")} == \
            {**{k: chosen[k] for k in ("voxel_size", "chosen", "config")}, "frames": 4}
    finally:
        proc.stop()


def test_a_named_family_fills_its_values_at_creation_and_explicit_values_win(server, client):
    session = client.create_session(voxel_size=0.01, sensor={"family": "hololens", "sigma0": 0.004})
    stats = session.stats()
    assert stats["sensor"] == "hololens" and stats["chosen"] == {"voxel_size": "set", "sensor": "set"}
    assert stats["config"]["sensor"]["sigma0"] == 0.004 and stats["config"]["sensor"]["sigma2"] is not None
