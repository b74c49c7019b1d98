"""The cluster's parts in this process, without Ray: routing by shard, eviction and restore, the merged
/metrics, and that nothing outside server/cluster/serve.py needs Ray."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

import httpx
import pytest

from server.cluster.ingress import LocalOwners, OwnerUnreachable, ingress_app
from server.cluster.metrics import merged, quantile
from server.cluster.owner import SessionOwner, session_of, shard_of
from server.metrics import SECONDS_BUCKETS, Histogram

from ..server.harness import REPO, TOKEN
from .conftest import MSGPACK, VOXEL, frame_body, request, run, settings

VIEW = {"K": [[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]], "width": 320, "height": 240}


def test_session_ids_route_by_a_stable_hash_and_each_owner_creates_only_its_own(tmp_path):
    owners = [SessionOwner(settings(tmp_path, owners=3), k) for k in range(3)]
    for k, owner in enumerate(owners):
        ids = [owner.store.new_session_id() for _ in range(20)]
        assert {shard_of(i, 3) for i in ids} == {k} and len(set(ids)) == 20
    assert shard_of("0" * 32, 3) == shard_of("0" * 32, 3) == int.from_bytes(
        __import__("hashlib").blake2b(b"0" * 32, digest_size=8).digest(), "little") % 3
    assert session_of("/v1/sessions/abc/frames") == session_of("/v1/sessions/abc") == "abc"
    assert session_of("/v1/sessions") is None and session_of("/healthz") is None


def test_quantiles_of_merged_histograms_interpolate_within_the_bucket():
    a, b = Histogram(), Histogram()
    for v in (0.003, 0.004, 0.02):
        a.observe(v)
    b.observe(0.02), b.observe(0.2)
    m = merged([(a.counts, a.sum), (b.counts, b.sum)])
    assert m.counts[:6] == [2, 0, 2, 0, 0, 1] and m.sum == pytest.approx(0.247)
    # rank 2.5 of 5 lies in (0.01, 0.025]: half of its 2 observations -> 0.01 + 0.015 * 0.25
    assert quantile(m, 0.5) == pytest.approx(0.01 + 0.015 * 0.25)
    assert quantile(m, 0.2) == pytest.approx(0.005 * 0.5)
    assert quantile(Histogram(), 0.5) == 0.0
    over = Histogram()
    over.observe(99.0)
    assert quantile(over, 0.95) == SECONDS_BUCKETS[-1]


def cluster_client(tmp_path, owners: int = 2, **overrides):
    parts = [SessionOwner(settings(tmp_path, owners=owners, api_token=TOKEN, **overrides), k) for k in range(owners)]
    app = ingress_app(parts[0].settings, LocalOwners(parts))
    client = httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://cluster",
                               headers={"Authorization": f"Bearer {TOKEN}"})
    return parts, client


def test_an_evicted_session_restores_to_the_same_digest_and_png_bytes_under_concurrent_requests(tmp_path, frames):
    # a budget of one byte: every request ends with an eviction of whatever is idle
    parts, client = cluster_client(tmp_path, owner_memory_bytes=1)
    view = {**VIEW, "c2w": frames[0]["c2w"].tolist()}

    async def scenario():
        async with client:
            sid = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
            other = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
            owner = parts[shard_of(sid, 2)]

            async def stream(session_id):
                for kwargs in frames:
                    r = await client.post(f"/v1/sessions/{session_id}/frames", content=frame_body(kwargs), headers=MSGPACK)
                    assert r.status_code == 200, r.text

            async def look(session_id):  # renders and stats racing the folds and evictions
                for _ in range(6):
                    r = await client.post(f"/v1/sessions/{session_id}/render", json=view)
                    assert r.status_code == 200, r.text
                    await asyncio.sleep(0)

            await asyncio.gather(stream(sid), stream(other), look(sid), look(other))
            before = (await client.get(f"/v1/sessions/{sid}/digest")).json()
            png = (await client.post(f"/v1/sessions/{sid}/render", json=view)).content
            await asyncio.gather(*(p._evicting for p in parts if p._evicting))  # the budget's own eviction
            await owner.evict(0)
            assert sid not in owner.store._sessions and sid in owner.store.evicted
            listed = {s["id"]: s for s in (await client.get("/v1/sessions")).json()["sessions"]}
            assert listed[sid]["frames"] == len(frames)  # listed without restoring it
            assert sid not in owner.store._sessions
            after = (await client.get(f"/v1/sessions/{sid}/digest")).json()
            assert after == before and (await client.post(f"/v1/sessions/{sid}/render", json=view)).content == png
            assert (await client.delete(f"/v1/sessions/{other}")).status_code == 200
            assert (await client.get(f"/v1/sessions/{other}")).status_code == 404
            return before, owner.store.evictions, owner.store.restores

    digest, evictions, restores = run(scenario())
    assert digest["frames"] == len(frames) and evictions >= 2 and restores >= 2
    single = SessionOwner(settings(tmp_path / "single", owners=1), 0)  # the same frames, never evicted

    async def reference():
        sid = (await request(single, "POST", "/v1/sessions", json.dumps({"voxel_size": VOXEL}).encode(),
                             {"Content-Type": "application/json"}))[1]["id"]
        for kwargs in frames:
            await request(single, "POST", f"/v1/sessions/{sid}/frames", frame_body(kwargs), MSGPACK)
        return (await request(single, "GET", f"/v1/sessions/{sid}/digest"))[1]["sha256"]

    assert run(reference()) == digest["sha256"]


def test_an_owners_sessions_carry_the_services_settings_created_and_restored(tmp_path, frames):
    """The settings a single-process service gives its sessions reach every owner's, new and restored
    after an eviction: the archive's retention (`none`: no frame kept, corrections 409), the undo
    records and the background corrections, and the memory budget (a fold that could pass it: 413)."""
    parts, client = cluster_client(tmp_path, owner_memory_bytes=1, archive_retention="none",
                                   correction_undo_frames=0, correction_background_frames=7)

    async def scenario():
        async with client:
            created = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()
            sid = created["id"]
            assert created["archive_retention"] == "none"
            r = await client.post(f"/v1/sessions/{sid}/frames", content=frame_body(frames[0]), headers=MSGPACK)
            assert r.status_code == 200, r.text
            owner = parts[shard_of(sid, 2)]
            await asyncio.gather(*(p._evicting for p in parts if p._evicting))
            await owner.evict(0)
            assert sid not in owner.store._sessions
            r = await client.delete(f"/v1/sessions/{sid}/frames/0")  # restores it first
            assert r.status_code == 409 and r.json()["error"]["field"] == "archive_retention", r.text
            session = owner.store.get(sid)  # restored (again, where the owner's budget evicted it after the request)
            assert (session.undo_depth, session.background_frames, session.budget) == (0, 7, owner.store.budget)
            assert session.budget is not None and session.archive is None

    run(scenario())
    parts, client = cluster_client(tmp_path / "small", memory_budget_bytes=1 << 20)

    async def over_budget():
        async with client:
            sid = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
            r = await client.post(f"/v1/sessions/{sid}/frames", content=frame_body(frames[0]), headers=MSGPACK)
            assert r.status_code == 413 and r.json()["error"]["field"] == "frame", r.text

    run(over_budget())


def test_a_numbered_frame_refused_at_the_ingress_stops_the_frames_behind_it_at_once(tmp_path, frames):
    """The guard refuses a body before any route runs, in the ingress: the session's owner, where the
    frames numbered after it wait, is told, so they are refused at once naming it, as in one process
    (not after frame_order_wait_s, told to send a frame that was sent)."""
    limit = len(frame_body(frames[0])) + 1000
    parts, client = cluster_client(tmp_path, max_body_bytes=limit)
    assert all(p.app.state.frame_refused.__self__ is p.store for p in parts)  # an owner's own guard tells its store

    async def scenario():
        async with client:
            sid = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
            frames_url = f"/v1/sessions/{sid}/frames"
            first = await client.post(frames_url, content=frame_body(frames[0]), headers={**MSGPACK, "Frame-Index": "0"})
            assert first.status_code == 200, first.text
            big = await client.post(frames_url, content=b"x" * (limit + 1), headers={**MSGPACK, "Frame-Index": "1"})
            assert big.status_code == 413, big.text
            start = time.perf_counter()
            behind = await client.post(frames_url, content=frame_body(frames[2]), headers={**MSGPACK, "Frame-Index": "2"})
            assert behind.status_code == 409 and time.perf_counter() - start < 10, behind.text
            assert "follows frame 1, which was refused (body: " in behind.json()["error"]["message"]
            resent = await client.post(frames_url, content=frame_body(frames[1]), headers={**MSGPACK, "Frame-Index": "1"})
            assert resent.status_code == 200, resent.text  # the stream goes on

    run(scenario())


def test_concurrent_creates_on_several_owners_never_pass_max_sessions(tmp_path):
    """max_sessions is the data directory's: owners that create at once take turns to count it."""
    parts, client = cluster_client(tmp_path, max_sessions=2)

    async def scenario():
        async with client:
            assert (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).status_code == 201
            answers = await asyncio.gather(*(client.post("/v1/sessions", json={"voxel_size": VOXEL}) for _ in range(6)))
            codes = sorted(r.status_code for r in answers)
            assert codes == [201, 409, 409, 409, 409, 409], [r.text for r in answers]
            assert all(r.json()["error"]["field"] == "max_sessions" for r in answers if r.status_code == 409)
            assert len((await client.get("/v1/sessions")).json()["sessions"]) == 2

    run(scenario())


def test_the_ingress_keeps_the_services_auth_errors_and_answers_429_for_a_lost_owner(tmp_path):
    parts, client = cluster_client(tmp_path, max_sessions=1, owner_restart_wait_s=0.5)

    class Gone(LocalOwners):
        async def call(self, shard, method, *args):
            raise OwnerUnreachable(f"owner {shard} is restarting (ActorDiedError)")

    async def scenario():
        async with client:
            r = await client.get("/v1/sessions", headers={"Authorization": "Bearer wrong"})
            assert r.status_code == 401 and r.json()["error"]["field"] == "Authorization"
            r = await client.get("/v1/sessions/" + "ab" * 16)
            assert r.status_code == 404 and r.json() == {"error": {"code": "not_found", "message": "session_id: no such session",
                                                                   "field": "session_id"}}
            r = await client.post("/v1/sessions", json={"voxel_size": -1})
            assert r.status_code == 422 and r.json()["error"]["field"] == "voxel_size"
            assert (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).status_code == 201
            r = await client.post("/v1/sessions", json={"voxel_size": VOXEL})
            assert r.status_code == 409 and r.json()["error"]["field"] == "max_sessions"
            assert (await client.get("/healthz")).json() == {"status": "ok", "sessions": 1}
            assert (await client.get("/healthz", headers={"Authorization": ""})).json() == {"status": "ok"}
            assert (await client.get("/nowhere")).status_code == 404
            r = await client.get("/v1/sessions/" + "ab" * 16 + "/events")  # a stream cannot cross an owner call
            assert r.status_code == 501 and r.json()["error"]["field"] == "path"
            r = await client.post("/v1/sessions/prune")  # no owner holds the whole shared directory
            assert r.status_code == 501 and "single-process" in r.json()["error"]["message"]
        gone = ingress_app(parts[0].settings, Gone(parts))
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=gone), base_url="http://cluster",
                                     headers={"Authorization": f"Bearer {TOKEN}"}) as lost:
            r = await lost.get("/v1/sessions/" + "ab" * 16 + "/digest")
            assert r.status_code == 429 and r.headers["Retry-After"] and r.json()["error"]["field"] == "session_id"
            text = (await lost.get("/metrics")).text
            assert "canonical_cluster_owners_unreachable 2" in text

    run(scenario())


def test_the_viewers_session_list_gathers_every_owners_sessions_and_a_closed_owner_answers_503(tmp_path, frames):
    parts, client = cluster_client(tmp_path, owners=3)

    async def scenario():
        async with client:
            made = []
            for _ in range(4):
                made.append((await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"])
            r = await client.post(f"/v1/sessions/{made[0]}/frames", content=frame_body(frames[0]), headers=MSGPACK)
            assert r.status_code == 200
            listed = (await client.get("/v1/viewer/sessions")).json()["sessions"]
            assert [s["id"] for s in listed] == made  # every owner's, by creation, as one service lists them
            assert listed[0]["frames"] == 1 and listed[0]["last_fold"] is not None and listed[1]["last_fold"] is None
            assert (await client.get("/v1/viewer/sessions", headers={"Authorization": "Bearer wrong"})).status_code == 401
            owner = parts[shard_of(made[0], 3)]
            await owner.close()  # a graceful stop: requests that still reach it are not folded into closed files
            r = await client.post(f"/v1/sessions/{made[0]}/frames", content=frame_body(frames[1]), headers=MSGPACK)
            assert r.status_code == 503 and r.headers["Retry-After"] and r.json()["error"]["code"] == "unavailable"

    run(scenario())


def test_owners_found_running_with_other_settings_or_past_the_count_are_replaced(tmp_path):
    serve = pytest.importorskip("server.cluster.serve")  # imports Ray
    ours = settings(tmp_path, owners=2)
    other_dir, fewer = settings(tmp_path / "other", owners=2), settings(tmp_path, owners=1)
    assert serve.owners_to_replace({0: ours.model_dump_json(), 1: ours.model_dump_json()}, ours) == []
    assert serve.owners_to_replace({0: other_dir.model_dump_json(), 1: ours.model_dump_json()}, ours) == [0]
    assert serve.owners_to_replace({0: ours.model_dump_json(), 1: None}, ours) == [1]  # an earlier version's
    assert serve.owners_to_replace({0: ours.model_dump_json(), 1: ours.model_dump_json()}, fewer) == [0, 1]
    assert serve.owners_to_replace({0: fewer.model_dump_json(), 1: fewer.model_dump_json(), 2: None}, fewer) == [1, 2]


def test_a_request_for_an_owner_not_running_is_never_sent_and_gets_429_after_the_restart_wait(tmp_path):
    """Ray holds a call to an actor that it cannot place (too few CPUs) for as long as that lasts: the
    ingress asks an owner it has not seen running for its pid first, and answers 429 once
    ``owner_restart_wait_s`` passes, not ``owner_timeout_s`` (300 s by default) later."""
    parts, _ = cluster_client(tmp_path, owner_restart_wait_s=0.5)

    class Unplaced(LocalOwners):
        def __init__(self, owners):
            super().__init__(owners)
            self.sent, self.placed = [], asyncio.Event()

        async def call(self, shard, method, *args):
            self.sent.append((shard, method))
            if shard == 1:
                await self.placed.wait()
            return await super().call(shard, method, *args)

    held_by_1, held_by_0 = parts[1].store.new_session_id(), parts[0].store.new_session_id()

    async def scenario():
        owners = Unplaced(parts)
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=ingress_app(parts[0].settings, owners)),
                                     base_url="http://cluster", headers={"Authorization": f"Bearer {TOKEN}"}) as http:
            r = await asyncio.wait_for(http.get(f"/v1/sessions/{held_by_1}/digest"), 60)  # a hang guard, not a timing
            assert r.status_code == 429 and r.headers["Retry-After"]
            assert "owner 1 is not running" in r.json()["error"]["message"] and "owner_restart_wait_s" in r.text
            assert (1, "pid") in owners.sent and (1, "handle") not in owners.sent  # the request itself was never sent
            assert (await http.get(f"/v1/sessions/{held_by_0}/digest")).status_code == 404  # owner 0 answers meanwhile
            owners.placed.set()  # Ray places owner 1: its requests go through again
            assert (await http.get(f"/v1/sessions/{held_by_1}/digest")).status_code == 404
            assert (1, "handle") in owners.sent

    run(scenario())


def test_the_folds_per_second_are_over_whole_windows_whoever_reads_them(tmp_path, frames, monkeypatch):
    """Two scrapers (Prometheus and a person with curl) each read the rate over a whole window, not
    over the moments since the other's read."""
    from server.cluster import owner

    monkeypatch.setattr(owner, "RATE_WINDOW_S", 0.5)
    parts, client = cluster_client(tmp_path)

    async def scenario():
        async with client:
            sid = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
            for kwargs in frames[:2]:
                await client.post(f"/v1/sessions/{sid}/frames", content=frame_body(kwargs), headers=MSGPACK)

    run(scenario())
    time.sleep(0.6)
    rates = [sum(p.report()["folds_per_second"] for p in parts) for _ in range(3)]  # read back to back
    assert rates[0] > 0 and rates[0] == rates[1] == rates[2]


def test_metrics_sum_the_owners_and_label_each_by_node_and_owner(tmp_path, frames):
    parts, client = cluster_client(tmp_path)

    async def scenario():
        async with client:
            for _ in range(2):
                sid = (await client.post("/v1/sessions", json={"voxel_size": VOXEL})).json()["id"]
                for kwargs in frames[:2]:
                    await client.post(f"/v1/sessions/{sid}/frames", content=frame_body(kwargs), headers=MSGPACK)
            return (await client.get("/metrics")).text

    text = run(scenario())
    lines = dict(line.rsplit(" ", 1) for line in text.splitlines() if not line.startswith("#"))
    assert lines["canonical_frames_folded_total"] == "4" and lines["canonical_fold_seconds_count"] == "4"
    assert lines["canonical_sessions"] == "2"
    per_owner = [int(lines[f'canonical_cluster_sessions{{node="{p.node}",owner="{p.shard}"}}']) for p in parts]
    assert per_owner == [len(p.store) for p in parts] and sum(per_owner) == 2
    assert float(lines['canonical_fold_seconds_quantile{quantile="0.5"}']) > 0
    # the single process's families of the owners' work, under the same names
    for name in ("canonical_colour_solves_running", "canonical_colour_solves_done_total", "canonical_viewer_superseded_total"):
        assert int(lines[name]) >= 0 and f"# TYPE {name} " in text


def test_the_single_process_service_and_the_owners_run_without_ray():
    code = ("import sys; sys.modules['ray'] = None\n"  # any import of ray now fails
            "from server.app import create_app; create_app()\n"
            "import client.cli, server.cluster.owner, server.cluster.ingress\n"
            "try:\n    import server.cluster.serve\nexcept ImportError: print('serve needs ray')\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "serve needs ray"


def test_cluster_options_without_cluster_are_refused_before_anything_starts(tmp_path):
    out = subprocess.run([sys.executable, "-m", "client.cli", "serve", "--owners", "2", "--data-dir", str(tmp_path)],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "--address and --owners need --cluster" in out.stderr
    assert not (tmp_path / "sessions").exists()
