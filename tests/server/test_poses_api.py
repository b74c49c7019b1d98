"""Pose corrections and frame removal over HTTP, on a real service process and real files: the
corrected session equals one streamed the corrected frames (digest), survives kill -9 at the
commit point, and bad input changes nothing."""

from __future__ import annotations

import threading
from urllib.parse import quote

import httpx
import numpy as np
import pytest

from canonical_core.scene.corrections import drift_walk
from client.sdk import CanonicalError, Client
from server.archive import ARCHIVE, SessionArchive

from .harness import VOXEL, ServerProcess, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.realdata]


def drifted(frames: list[dict], seed: int = 0) -> list[dict]:
    """The frames (add_frame kwargs) with a random walk on their poses (1 cm and 0.5 degrees per frame)."""
    walk = drift_walk(len(frames), 0.01, 0.5, seed=seed)
    return [{**kwargs, "c2w": T @ kwargs["c2w"]} for kwargs, T in zip(frames, walk)]


def streamed(client: Client, frames: list[dict], **settings):
    session = client.create_session(voxel_size=VOXEL, **settings)
    for kwargs in frames:
        session.add_frame(**kwargs)
    return session


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("poses")
    proc = ServerProcess(root / "data", root / "server.log", snapshot_every_seconds=3600, snapshot_every_frames=4,
                         warm_up="false")
    proc.start()
    yield proc
    proc.kill9()


@pytest.fixture(scope="module")
def api(service):
    with Client(service.url) as c:
        yield c


@pytest.fixture(scope="module")
def few(frames) -> list[dict]:
    return frames[:6]


def test_correction_equals_streaming_the_true_poses(api, few):
    session = streamed(api, drifted(few))
    clean = streamed(api, few).digest()["sha256"]
    assert session.digest()["sha256"] != clean
    done = session.update_poses({kw["frame_id"]: kw["c2w"] for kw in few})
    assert done["corrected"] == len(few) and done["frames"] == len(few)
    assert session.digest()["sha256"] == clean
    stats = session.stats()
    assert stats["archive_retention"] == "all" and stats["archive_frames"] == len(few) and stats["archive_bytes"] > 0
    assert stats["undo_bytes"] > 0  # the re-fold's folds can be rolled back again


def test_removal_equals_streaming_the_rest(api, frames):
    session = streamed(api, frames)
    rng = np.random.default_rng(7)
    gone = sorted(rng.choice(len(frames), len(frames) // 3, replace=False).tolist())
    session.remove_frame(frames[gone[0]]["frame_id"])  # one DELETE
    session.update_poses({}, remove=[frames[k]["frame_id"] for k in gone[1:]])  # the rest as one request
    rest = [kw for k, kw in enumerate(frames) if k not in gone]
    assert session.digest()["sha256"] == streamed(api, rest).digest()["sha256"]
    # folding goes on from the corrected scene as it would from the fresh one; a removed id may be sent again
    session.add_frame(**frames[gone[0]])
    assert session.digest()["sha256"] == streamed(api, rest + [frames[gone[0]]]).digest()["sha256"]


def test_correcting_frames_after_the_snapshot_refolds_from_it(api, few):
    """The service snapshots every 4 frames: a correction of frames 4 and 5 starts from the snapshot
    of frames 0-3, and equals streaming the corrected frames all the same; then one of frame 1
    re-folds everything."""
    bad = drifted(few)
    session = streamed(api, bad)
    assert session.stats()["snapshot_frames"] == 4
    session.update_poses({kw["frame_id"]: kw["c2w"] for kw in few[4:]})
    assert session.digest()["sha256"] == streamed(api, bad[:4] + few[4:]).digest()["sha256"]
    session.update_poses({few[1]["frame_id"]: few[1]["c2w"]})
    assert session.digest()["sha256"] == streamed(api, bad[:1] + few[1:2] + bad[2:4] + few[4:]).digest()["sha256"]


def test_frames_without_ids_are_named_by_arrival_index(api, few):
    plain = [{**kw, "frame_id": None} for kw in few[:4]]
    session = streamed(api, plain)
    session.remove_frame(1)
    session.update_poses({"2": drifted(plain)[2]["c2w"]})
    expected = [plain[0], {**plain[2], "c2w": drifted(plain)[2]["c2w"]}, plain[3]]
    assert session.digest()["sha256"] == streamed(api, expected).digest()["sha256"]


@pytest.mark.parametrize("body, field", [
    ({"poses": {"nope": np.eye(4).tolist()}}, "poses.nope"),
    ({"poses": {"999": np.eye(4).tolist()}}, "poses.999"),
    ({"poses": {"F": np.diag([2.0, 1, 1, 1]).tolist()}}, "poses.F"),  # not rigid
    ({"poses": {"F": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}}, "poses.F.0"),  # 3x3
    ({"poses": {"F": "eye"}}, "poses.F"),
    ({"remove": ["nope"]}, "frames.nope"),
    ({"poses": {"odd key: ü": np.eye(4).tolist()}}, "poses.odd key: ü"),  # keys the message alone cannot delimit
    ({"remove": ["a: b"]}, "frames.a: b"),
    ({"remove": [""]}, "frames."),
    ({"remove": ["9" * 4301]}, "frames." + "9" * 4301),  # once CPython's digit limit, with no field
    ({"poses": {"9" * 4301: np.eye(4).tolist()}}, "poses." + "9" * 4301),
    ({}, "poses"),
    ({"poses": {}, "extra": 1}, "extra"),
])
def test_bad_corrections_name_the_field_and_change_nothing(service, api, few, body, field):
    session = streamed(api, few[:2])
    key = few[1]["frame_id"]
    body = {k: ({key if p == "F" else p: v for p, v in val.items()} if k == "poses" else val) for k, val in body.items()}
    field = field.replace(".F", f".{key}")
    before = session.digest()["sha256"]
    r = httpx.post(f"{service.url}/v1/sessions/{session.id}/poses", json=body, timeout=60)
    assert r.status_code == 422, r.text
    assert r.json()["error"]["field"] == field
    assert session.digest()["sha256"] == before


def test_errors_name_frame_keys_with_any_character(service, api, few):
    """A frame_id holding spaces, colons or non-ASCII: every error of /poses and DELETE /frames names
    ``poses.<key>`` or ``frames.<key>`` exactly, and nothing changes."""
    key = "shelf: frame #1 ü"
    session = streamed(api, [few[0], {**few[1], "frame_id": key}])
    before = session.digest()["sha256"]
    for bad, field in ((np.diag([2.0, 1, 1, 1]), f"poses.{key}"), (np.full((4, 4), np.nan), f"poses.{key}")):
        r = httpx.post(f"{service.url}/v1/sessions/{session.id}/poses",
                       content='{"poses": {"%s": %s}}' % (key, str(bad.tolist()).replace("nan", "NaN")),
                       headers={"content-type": "application/json"}, timeout=60)
        assert r.status_code == 422 and r.json()["error"]["field"] == field, r.text
    r = httpx.delete(f"{service.url}/v1/sessions/{session.id}/frames/{quote(key + ' x', safe='')}", timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == f"frames.{key} x", r.text
    assert session.digest()["sha256"] == before
    session.remove_frame(key)  # the odd key itself names the frame
    assert session.digest()["sha256"] == streamed(api, few[:1]).digest()["sha256"]


def test_frame_ids_with_slashes_or_dot_segments_name_their_frames(service, api, few):
    """DELETE .../frames/{key} reaches a frame_id holding '/' (sent as is or as %2F), '.' and '..'
    sent as %2E and %2E%2E (a client resolves them as they are, as path segments), and a line break."""
    keys = ["shelf/1", "a/b/", ".", "..", "line 1\nline 2"]
    assert len(few) > len(keys)
    session = streamed(api, [few[0]] + [{**kw, "frame_id": key} for kw, key in zip(few[1:], keys)])
    for sent in ("shelf/1", "a%2Fb%2F", "%2E", "%2E%2E", "line%201%0Aline%202"):
        r = httpx.delete(httpx.URL(f"{service.url}/v1/sessions/{session.id}/frames/{sent}"), timeout=60)
        assert r.status_code == 200 and r.json()["removed"] == 1, (sent, r.text)
    assert session.digest()["sha256"] == streamed(api, few[:1]).digest()["sha256"]


def test_integer_keys_are_arrival_indices_whatever_the_frame_ids(api, few):
    """Frame ids that are numbers (a capture's line numbers) and arrival indices: an integer key is an
    arrival index (as in the library), a string a frame_id first, over HTTP as in process."""
    numbered = [{**kw, "frame_id": str(k + 1)} for k, kw in enumerate(few[:4])]
    shift = np.eye(4)
    shift[:3, 3] = [0.02, 0.0, 0.0]
    moved = [{**kw, "c2w": shift @ kw["c2w"]} if k == 1 else kw for k, kw in enumerate(numbered)]
    session = streamed(api, numbered)
    session.update_poses({1: shift @ numbered[1]["c2w"]})  # arrival 1, whose frame_id is "2"
    assert session.digest()["sha256"] == streamed(api, moved).digest()["sha256"]
    session.remove_frame(1)  # arrival 1
    assert session.digest()["sha256"] == streamed(api, [numbered[k] for k in (0, 2, 3)]).digest()["sha256"]
    session.update_poses({}, remove=["1"])  # frame_id "1": arrival 0
    assert session.digest()["sha256"] == streamed(api, [numbered[k] for k in (2, 3)]).digest()["sha256"]
    with pytest.raises(CanonicalError) as info:  # one frame named both ways in one request
        session.update_poses({2: numbered[2]["c2w"], "3": numbered[2]["c2w"]})
    assert info.value.status == 422 and info.value.field in ("poses.2", "poses.3")


def test_retention_is_chosen_per_session(service, api, few):
    """``archive_retention`` at creation overrides the service's default, shows in the session's info,
    and a bad value is a 422 naming it that creates nothing."""
    none = streamed(api, few[:2], archive_retention="none")
    keyframes = api.create_session(voxel_size=VOXEL, archive_retention="keyframes")
    default = api.create_session(voxel_size=VOXEL)
    assert [s.stats()["archive_retention"] for s in (none, keyframes, default)] == ["none", "keyframes", "all"]
    listed = {s["id"]: s["archive_retention"] for s in api.sessions()}
    assert listed[none.id] == "none" and listed[keyframes.id] == "keyframes"
    with pytest.raises(CanonicalError) as info:
        none.update_poses({few[0]["frame_id"]: few[0]["c2w"]})
    assert info.value.status == 409 and info.value.field == "archive_retention"
    count = len(api.sessions())
    for bad in ("some", 3, None):
        r = httpx.post(f"{service.url}/v1/sessions", json={"voxel_size": VOXEL, "archive_retention": bad}, timeout=60)
        if bad is None:  # null: the service's default
            assert r.status_code == 201 and r.json()["archive_retention"] == "all", r.text
            count += 1
            continue
        assert r.status_code == 422 and r.json()["error"]["field"] == "archive_retention", r.text
    assert len(api.sessions()) == count


def test_nan_pose_is_refused(service, api, few):
    session = streamed(api, few[:2])
    before = session.digest()["sha256"]
    key = few[0]["frame_id"]
    body = '{"poses": {"%s": [[1, 0, 0, NaN], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}' % key  # Python's JSON reads NaN
    r = httpx.post(f"{service.url}/v1/sessions/{session.id}/poses", content=body,
                   headers={"content-type": "application/json"}, timeout=60)
    assert r.status_code == 422 and r.json()["error"]["field"] == f"poses.{key}", r.text
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match=rf"^poses\.{key}: contains NaN"):  # the SDK says so before sending
        session.update_poses({key: bad})
    with pytest.raises(CanonicalError) as info:
        session.remove_frame("not-a-frame")
    assert info.value.status == 422 and info.value.field == "frames.not-a-frame"
    assert session.digest()["sha256"] == before


def test_a_session_without_archive_refuses_corrections(tmp_path, few):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", archive_retention="none", warm_up="false").start()
    try:
        with Client(proc.url) as c:
            session = streamed(c, few[:2])
            before = session.digest()["sha256"]
            for call in (lambda: session.update_poses({few[0]["frame_id"]: few[0]["c2w"]}),
                         lambda: session.remove_frame(few[0]["frame_id"])):
                with pytest.raises(CanonicalError) as info:
                    call()
                assert info.value.status == 409 and info.value.field == "archive_retention"
            assert session.digest()["sha256"] == before and session.stats()["archive_bytes"] == 0
    finally:
        proc.kill9()


def test_keyframes_retention_refolds_the_kept_frames(tmp_path, frames):
    proc = ServerProcess(tmp_path / "data", tmp_path / "server.log", archive_retention="keyframes", warm_up="false").start()
    try:
        with Client(proc.url) as c:
            session = streamed(c, drifted(frames[:7]))
            assert session.stats()["archive_frames"] == 2  # arrivals 0 and 5
            before = session.digest()["sha256"]
            with pytest.raises(CanonicalError) as info:  # a frame it does not keep: its pose could not be used
                session.update_poses({frames[1]["frame_id"]: frames[1]["c2w"]})
            assert info.value.status == 422 and info.value.field == f"poses.{frames[1]['frame_id']}"
            assert "does not keep this frame" in str(info.value) and session.digest()["sha256"] == before
            done = session.update_poses({frames[0]["frame_id"]: frames[0]["c2w"]})
            assert done["dropped"] == 5 and done["frames"] == 2
            kept = [frames[0], drifted(frames[:7])[5]]
            assert session.digest()["sha256"] == streamed(c, kept).digest()["sha256"]
    finally:
        proc.kill9()


def test_kill9_after_the_correction_is_archived_restarts_corrected(tmp_path, few):
    """The commit point is the archived correction: killed right after it (before the snapshot), the
    restart re-folds; killed after the acknowledgement, the restart loads the corrected snapshot."""
    data = tmp_path / "data"
    proc = ServerProcess(data, tmp_path / "server.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:
        with Client(proc.url) as c:
            acked = streamed(c, drifted(few))
            acked.update_poses({kw["frame_id"]: kw["c2w"] for kw in few[:3]})
            acked_digest = acked.digest()["sha256"]
            mid = streamed(c, drifted(few))
            clean = streamed(c, few).digest()["sha256"]
            expected_acked = streamed(c, few[:3] + drifted(few)[3:]).digest()["sha256"]
    finally:
        proc.kill9()
    # the state a kill -9 leaves between archiving a correction and snapshotting its scene
    archive = SessionArchive(data / "sessions" / mid.id / ARCHIVE, "all")
    archive.append_correction({k: kw["c2w"] for k, kw in enumerate(few)}, [])
    archive.close()
    proc = ServerProcess(data, tmp_path / "server2.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:
        with Client(proc.url) as c:
            assert c.session(acked.id).digest()["sha256"] == acked_digest == expected_acked
            assert c.session(mid.id).digest()["sha256"] == clean
    finally:
        proc.kill9()
    proc = ServerProcess(data, tmp_path / "server3.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:  # the re-fold was snapshotted: a second restart loads it (same digest), and frames go on
        with Client(proc.url) as c:
            assert c.session(mid.id).digest()["sha256"] == clean
    finally:
        proc.kill9()


def test_correction_racing_a_fold_is_refused_or_ordered(api, frames):
    """A frame folded while a correction is computed: the correction gets 409 and changes nothing, or
    it finished first and the frame folded on the corrected scene; never a mixture."""
    session = streamed(api, drifted(frames[:8]))
    outcome: dict = {}

    def correct():
        try:
            outcome["done"] = session.update_poses({kw["frame_id"]: kw["c2w"] for kw in frames[:8]})
        except CanonicalError as exc:
            outcome["error"] = exc

    worker = threading.Thread(target=correct)
    worker.start()
    session.add_frame(**frames[8])
    worker.join()
    if "error" in outcome:
        assert outcome["error"].status == 409 and outcome["error"].field == "session_id"
        expected = drifted(frames[:8]) + [frames[8]]
    else:
        expected = frames[:9]
    assert session.digest()["sha256"] == streamed(api, expected).digest()["sha256"]


def test_long_corrections_refold_in_the_background_and_a_restart_finishes_them(tmp_path, few, capsys):
    """With corrections of more than 2 frames in the background: POST /poses answers 202, the SDK polls
    to the result and the CLI shows progress; a kill -9 right after the 202 restarts corrected, and
    the status then says done."""
    from client import cli

    data = tmp_path / "data"
    proc = ServerProcess(data, tmp_path / "server.log", snapshot_every_seconds=3600, correction_background_frames=2,
                         warm_up="false").start()
    try:
        with Client(proc.url) as c:
            clean = streamed(c, few).digest()["sha256"]
            polled = streamed(c, drifted(few))
            seen = []
            done = polled.update_poses({kw["frame_id"]: kw["c2w"] for kw in few}, progress=seen.append)
            assert done["state"] == "done" and done["corrected"] == len(few) and polled.digest()["sha256"] == clean
            assert seen and seen[0]["state"] == "pending" and seen[-1]["state"] == "done"  # the 202: as accepted
            assert polled.correction(seen[0]["correction_id"])["result"]["frames"] == len(few)
            with pytest.raises(CanonicalError) as info:
                polled.correction("nope")
            assert info.value.status == 404 and info.value.field == "correction_id"
            shown = streamed(c, drifted(few))
            path = tmp_path / "true.txt"
            path.write_text("".join(f"{kw['frame_id']} " + " ".join(map(repr, kw["c2w"].reshape(16).tolist())) + "\n"
                                    for kw in few))
            assert cli.main(["poses", str(path), "--session", shown.id, "--url", proc.url]) == 0
            assert "frames re-folded" in capsys.readouterr().err and shown.digest()["sha256"] == clean
            killed = streamed(c, drifted(few))
            status = killed.update_poses({kw["frame_id"]: kw["c2w"] for kw in few}, wait=False)
            assert status["state"] == "pending" and status["correction_id"]
    finally:
        proc.kill9()
    proc = ServerProcess(data, tmp_path / "server2.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:
        with Client(proc.url) as c:
            session = c.session(killed.id)
            assert session.digest()["sha256"] == clean
            after = session.correction(status["correction_id"])  # what a client polling through the restart reads
            assert after["state"] == "done" and after["result"] == {
                "id": killed.id, "frames": len(few), "frames_before": len(few), "corrected": len(few), "removed": 0,
                "dropped": 0, "state": "done", "correction_id": status["correction_id"]}
    finally:
        proc.kill9()


def test_a_background_correction_that_fails_is_undone_and_the_session_goes_on(tmp_path, few):
    """A correction answered 202 whose re-fold fails (a pose moved 3 m passes the session's voxel cap)
    is undone in the archive: the old scene is served and takes frames, its status says failed with
    the reason before and after a restart (a graceful one and a kill -9), a restart neither retries it
    nor counts it, and a later correction re-folds the frames as they were."""
    data = tmp_path / "data"
    proc = ServerProcess(data, tmp_path / "server.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:
        with Client(proc.url) as c:
            voxels = streamed(c, few[:4]).stats()["voxels"]
            session = streamed(c, few[:4], max_voxels=int(voxels * 1.2))  # room for its frames, not for the move
            before = session.digest()["sha256"]
            far = few[0]["c2w"].copy()
            far[:3, 3] += 3.0
            accepted = session.update_poses({few[0]["frame_id"]: far}, wait=False)
            assert accepted["state"] == "pending"
            assert wait_for(lambda: session.correction(accepted["correction_id"])["state"] == "failed", 60)
            failed = session.correction(accepted["correction_id"])
            assert "max_voxels" in failed["error"], failed
            assert session.digest()["sha256"] == before
            session.add_frame(**few[4])  # frames go on
            served = session.digest()["sha256"]
    finally:
        proc.stop()
    for kill in (False, True):
        proc = ServerProcess(data, tmp_path / f"server_{kill}.log", snapshot_every_seconds=3600, warm_up="false").start()
        try:
            with Client(proc.url) as c:
                again = c.session(session.id)
                assert again.digest()["sha256"] == served
                status = again.correction(failed["correction_id"])
                assert status["state"] == "failed" and "max_voxels" in status["error"]
        finally:
            proc.kill9() if kill else proc.stop()
    proc = ServerProcess(data, tmp_path / "server_last.log", snapshot_every_seconds=3600, warm_up="false").start()
    try:
        with Client(proc.url) as c:
            again = c.session(session.id)
            done = again.update_poses({few[1]["frame_id"]: few[1]["c2w"]})  # its own pose: the same frames
            assert done["state"] == "done" and again.digest()["sha256"] == served
    finally:
        proc.stop()
