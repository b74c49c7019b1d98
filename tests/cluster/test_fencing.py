"""One writer per session: two owners of one session folder (forced: both think they own it). The
stale owner's appends and snapshots fail and fold nothing; the log stays one ordered, CRC-valid stream."""

from __future__ import annotations

import json
import os

import pytest

from canonical_core import SceneConfig
from server.cluster.lease import EPOCH, Lease
from server.cluster.owner import SessionOwner
from server.framelog import Fenced, scan
from server.durability import LOG, SNAPSHOT, restore_scene

from .conftest import MSGPACK, VOXEL, frame_body, reference_digest, request, run, settings


def test_a_lease_counts_owners_and_fences_every_earlier_one(tmp_path):
    first, second = Lease(tmp_path), Lease(tmp_path)
    with first.take() as epoch:
        assert epoch == 1
    with first.held(), first.held():  # re-entrant in its process
        pass
    with second.take() as epoch:
        assert epoch == 2 and second.current() == 2
    with pytest.raises(Fenced, match="another owner took the session"):
        with first.held():
            raise AssertionError("the stale owner's block must not run")
    with second.held():
        pass
    assert (tmp_path / EPOCH).read_bytes() == (2).to_bytes(8, "little")
    first.close(), second.close()


def test_two_owners_of_one_session_the_stale_one_folds_nothing_and_the_log_stays_one_stream(tmp_path, frames):
    # two owner processes' worth of state on one data directory, both shard 0 of 1: each takes any id
    stale, fresh = SessionOwner(settings(tmp_path, owners=1), 0), SessionOwner(settings(tmp_path, owners=1), 0)

    async def scenario():
        status, created = await request(stale, "POST", "/v1/sessions", json.dumps({"voxel_size": VOXEL}).encode(),
                                        {"Content-Type": "application/json"})
        assert status == 201
        sid = created["id"]
        path = f"/v1/sessions/{sid}"
        for kwargs in frames[:3]:
            assert (await request(stale, "POST", f"{path}/frames", frame_body(kwargs), MSGPACK))[0] == 200
        held_by_stale = stale.store._sessions[sid]
        status, digest = await request(fresh, "GET", f"{path}/digest")  # the new owner restores: it takes the lease
        assert status == 200 and digest["frames"] == 3
        log_before = (tmp_path / "sessions" / sid / LOG).read_bytes()
        status, error = await request(stale, "POST", f"{path}/frames", frame_body(frames[3]), MSGPACK)
        assert status == 503 and error["error"]["field"] == "data_dir" and "another owner" in error["error"]["message"]
        assert held_by_stale.scene.frames == 3 and held_by_stale.stale  # folded nothing
        assert (tmp_path / "sessions" / sid / LOG).read_bytes() == log_before  # wrote nothing
        held_by_stale.snapshot()  # nor can it snapshot (which would also restart the log under the new owner)
        assert not (tmp_path / "sessions" / sid / SNAPSHOT).exists()
        for kwargs in frames[3:6]:
            assert (await request(fresh, "POST", f"{path}/frames", frame_body(kwargs), MSGPACK))[0] == 200
        return sid, (await request(fresh, "GET", f"{path}/digest"))[1]

    sid, digest = run(scenario())
    folder = tmp_path / "sessions" / sid
    found = scan((folder / LOG).read_bytes())
    assert not found.damaged and not found.torn and found.end == found.size
    assert [r.index for r in found.records] == list(range(6))
    assert digest["sha256"] == reference_digest(frames[:6])
    restored = restore_scene(folder, SceneConfig(voxel_size=VOXEL))  # what the next owner would read
    assert restored.scene.digest() == digest["sha256"]
    restored.log.close()


def test_the_stale_owner_takes_the_session_back_only_by_reading_it_again(tmp_path, frames):
    """A request that reaches the stale owner again (routing moved back) restores the session, taking a
    new lease, so it continues from every frame the other owner logged."""
    first, second = SessionOwner(settings(tmp_path, owners=1), 0), SessionOwner(settings(tmp_path, owners=1), 0)

    async def scenario():
        sid = (await request(first, "POST", "/v1/sessions", json.dumps({"voxel_size": VOXEL}).encode(),
                             {"Content-Type": "application/json"}))[1]["id"]
        path = f"/v1/sessions/{sid}"
        await request(first, "POST", f"{path}/frames", frame_body(frames[0]), MSGPACK)
        await request(second, "POST", f"{path}/frames", frame_body(frames[1]), MSGPACK)
        assert (await request(first, "POST", f"{path}/frames", frame_body(frames[2]), MSGPACK))[0] == 503
        assert (await request(first, "POST", f"{path}/frames", frame_body(frames[2]), MSGPACK))[0] == 200
        assert (await request(second, "POST", f"{path}/frames", frame_body(frames[3]), MSGPACK))[0] == 503
        return (await request(first, "GET", f"{path}/digest"))[1]

    digest = run(scenario())
    assert digest["frames"] == 3 and digest["sha256"] == reference_digest(frames[:3])
    assert os.path.getsize(tmp_path / "sessions" / digest["id"] / EPOCH) == 8
