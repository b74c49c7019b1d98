"""Retention: the policy as a pure function of the sessions' last activity, sizes, now and the settings
(time to live, disk budget oldest-idle-first, the 24-hour floor, busy sessions); the store applying it
through its delete (dry run, a session whose lock is held, an unavailable one); and a real service
pruning sessions whose files were made old with os.utime, by the CLI and by its own periodic loop."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import httpx
import pytest

from canonical_core import SceneConfig
from client.sdk import Client
from server.retention import FLOOR_S, Candidate, folder_usage, plan
from server.session_errors import SessionNotFound
from server.store import SessionStore
from tests.client.test_cli_errors import canonical

from .harness import TOKEN, VOXEL, ServerProcess, wait_for
from .test_store import store  # noqa: F401  (the fixture: an opened store in tmp_path)

NOW = 1_700_000_000.0
DAY = 86400.0


def idle(name: str, days: float, size: int = 100, busy: bool = False) -> Candidate:
    return Candidate(name, NOW - days * DAY, size, busy)


def ids(removals) -> list[str]:
    return [r.id for r in removals]


def test_a_session_idle_longer_than_the_ttl_is_removed_and_the_others_are_kept():
    sessions = [idle("new", 0.5), idle("week", 7.2), idle("days", 3)]
    assert [(r.id, r.reason) for r in plan(sessions, 300, NOW, 7 * DAY, None)] == [("week", "ttl")]
    assert plan(sessions, 300, NOW, None, None) == []  # the defaults: neither a ttl nor a budget


def test_the_disk_budget_removes_the_oldest_idle_sessions_first_until_it_is_met():
    sessions = [idle("two", 2, 100), idle("five", 5, 100), idle("three", 3, 100), idle("fresh", 0.1, 100)]
    chosen = plan(sessions, 450, NOW, None, 250)
    assert ids(chosen) == ["five", "three"] and {r.reason for r in chosen} == {"disk_budget"}
    assert plan(sessions, 450, NOW, None, 450) == []  # at the budget: nothing
    # the time to live goes first, then the budget counts what it freed
    assert [(r.id, r.reason) for r in plan(sessions, 450, NOW, 4 * DAY, 300)] == [("five", "ttl"), ("three", "disk_budget")]


@pytest.mark.parametrize("ttl_s, budget", [(1.0, 1), (1e-9, 1), (None, 1), (1.0, None)])
def test_no_session_active_in_the_last_24_hours_is_removed_whatever_the_settings(ttl_s, budget):
    recent = [Candidate(f"s{k}", NOW - age, 10**9) for k, age in enumerate((0, 1, 3600, FLOOR_S - 1, FLOOR_S))]
    future = Candidate("clock-went-back", NOW + 3600, 10**9)
    assert plan([*recent, future], 10**12, NOW, ttl_s, budget) == []
    assert ids(plan([*recent, Candidate("old", NOW - FLOOR_S - 1, 1)], 10**12, NOW, ttl_s, budget)) == ["old"]


def test_a_busy_session_is_never_chosen():
    sessions = [idle("busy", 30, busy=True), idle("idle", 20)]
    assert ids(plan(sessions, 10**6, NOW, 1.0, 1)) == ["idle"]


def make_old(path: Path, seconds: float) -> float:
    """Set the modification time of the folder and everything under it ``seconds`` into the past."""
    then = time.time() - seconds
    for root, dirs, files in os.walk(path):
        for name in (*dirs, *files):
            os.utime(os.path.join(root, name), (then, then))
    os.utime(path, (then, then))
    return then


def test_the_store_removes_through_its_delete_and_a_dry_run_removes_nothing(store):
    old, older, fresh = (store.create(SceneConfig(voxel_size=0.01)) for _ in range(3))
    make_old(old.path, 3 * DAY)
    then = make_old(older.path, 4 * DAY)
    assert folder_usage(older.path).last_active == pytest.approx(then)
    assert old.summary()["last_active"] == pytest.approx(then + DAY)

    report = store.prune(1.0, None, dry_run=True)
    assert report["dry_run"] and [r["id"] for r in report["removed"]] == [older.id, old.id]
    assert {s.id for s in store.list()} == {old.id, older.id, fresh.id} and old.path.is_dir() and older.path.is_dir()

    report = store.prune(1.0, None)
    assert [r["id"] for r in report["removed"]] == [older.id, old.id] and report["freed_bytes"] > 0
    assert [s.id for s in store.list()] == [fresh.id]
    assert sorted(p.name for p in store.root.iterdir()) == [fresh.id]  # no folder, no tombstone left
    assert old.deleted and older.deleted
    with pytest.raises(SessionNotFound):
        store.get(old.id)


def test_a_session_whose_lock_is_held_survives_and_goes_once_it_is_idle(store):
    busy = store.create(SceneConfig(voxel_size=0.01))
    make_old(busy.path, 3 * DAY)
    with busy.lock:  # a frame folding, a snapshot committing, a correction re-folding in the request
        assert store.prune(1.0, 1)["removed"] == []
    assert store.get(busy.id) is busy

    # locked between the plan and the removal: kept too (delete does not wait for the lock)
    held = threading.Event()
    release = threading.Event()

    def fold_meanwhile(session):
        with busy.lock:
            held.set()
            release.wait(10)
    thread = threading.Thread(target=fold_meanwhile, args=(busy,))
    original = store.delete

    def delete_after_a_frame_arrived(session_id, keep_if=None):
        thread.start()
        held.wait(10)
        try:
            return original(session_id, keep_if=keep_if)
        finally:
            release.set()
    store.delete = delete_after_a_frame_arrived
    try:
        assert store.prune(1.0, 1)["removed"] == []
    finally:
        thread.join(10)
        del store.delete
    assert store.get(busy.id) is busy
    assert [r["id"] for r in store.prune(1.0, 1)["removed"]] == [busy.id]


def test_a_session_reached_after_the_plan_is_kept(store):
    session = store.create(SceneConfig(voxel_size=0.01))
    make_old(session.path, 3 * DAY)
    original = store.delete

    def delete_after_a_write(session_id, keep_if=None):
        (session.path / "meta.json").touch()  # what a frame's log append does to the folder's newest time
        return original(session_id, keep_if=keep_if)
    store.delete = delete_after_a_write
    try:
        assert store.prune(1.0, 1)["removed"] == []
    finally:
        del store.delete
    assert store.get(session.id) is session


def test_an_unavailable_session_counts_towards_the_disk_but_is_kept(tmp_path):
    damaged = tmp_path / "sessions" / ("d" * 32)
    damaged.mkdir(parents=True)
    (damaged / "frames.log").write_bytes(b"x" * 5000)  # no meta.json: unavailable
    make_old(damaged, 30 * DAY)
    store = SessionStore(tmp_path, max_sessions=8)
    store.open()
    try:
        assert damaged.name in store.unavailable
        report = store.prune(1.0, 1)
        assert report["removed"] == [] and report["data_dir_bytes"] >= 5000 and damaged.is_dir()
    finally:
        store.close()


def test_the_service_prunes_by_the_cli_and_by_its_periodic_loop(tmp_path, frames):
    """Sessions made old with os.utime while the service is stopped; a TTL of 1 s and a budget of 1 byte
    remove them, never the one that received a frame just now."""
    data = tmp_path / "data"
    settings = {"session_ttl_s": 1, "disk_budget_bytes": 1, "warm_up": "false", "snapshot_every_seconds": 3600}
    server = ServerProcess(data, tmp_path / "server.log", token=TOKEN, retention_every_s=3600, **settings).start()
    try:
        with Client(server.url, token=TOKEN) as client:
            made = [client.create_session(voxel_size=VOXEL) for _ in range(3)]
            for session, frame in zip(made, frames):
                session.add_frame(**frame)
    finally:
        server.stop()
    week, days, fresh = (s.id for s in made)
    make_old(data / "sessions" / week, 7 * DAY)
    make_old(data / "sessions" / days, 2 * DAY)

    server.start()
    try:
        url = ["--url", server.url, "--token", TOKEN]
        listed = {s["id"]: s for s in httpx.get(f"{server.url}/v1/sessions", headers=auth()).json()["sessions"]}
        assert time.time() - listed[week]["last_active"] == pytest.approx(7 * DAY, abs=600)
        assert time.time() - listed[fresh]["last_active"] < 600

        dry = canonical("sessions", "--prune", "--dry-run", "--json", *url)
        assert dry.returncode == 0, dry.stderr
        report = json.loads(dry.stdout)
        assert report["dry_run"] and [r["id"] for r in report["removed"]] == [week, days]
        assert {r["reason"] for r in report["removed"]} == {"ttl"} and report["floor_s"] == FLOOR_S
        assert "would remove 2 sessions" in dry.stderr
        assert session_ids(server) == {week, days, fresh} and (data / "sessions" / week).is_dir()

        pruned = canonical("sessions", "--prune", *url)
        assert pruned.returncode == 0, pruned.stderr
        assert [line.split()[:2] for line in pruned.stdout.splitlines()] == [[week, "ttl"], [days, "ttl"]]
        assert "removed 2 sessions" in pruned.stderr
        assert session_ids(server) == {fresh}
        assert sorted(p.name for p in (data / "sessions").iterdir()) == [fresh]
        assert httpx.get(f"{server.url}/v1/sessions/{week}", headers=auth()).status_code == 404

        assert canonical("sessions", "--dry-run", *url).returncode != 0  # --dry-run alone is refused
        assert httpx.post(f"{server.url}/v1/sessions/prune").status_code == 401
    finally:
        server.stop()

    make_old(data / "sessions" / fresh, 2 * DAY)
    server = ServerProcess(data, tmp_path / "server.log", token=TOKEN, retention_every_s=0.2, **settings).start()
    try:
        assert wait_for(lambda: session_ids(server) == set(), timeout=30), server.log()
        # unlisted at once; the folder goes once its tombstone (`.deleted-<id>`) is removed, just after
        assert wait_for(lambda: list((data / "sessions").iterdir()) == [], timeout=30), list((data / "sessions").iterdir())
    finally:
        server.stop()


def auth() -> dict:
    return {"Authorization": f"Bearer {TOKEN}"}


def session_ids(server) -> set[str]:
    return {s["id"] for s in httpx.get(f"{server.url}/v1/sessions", headers=auth()).json()["sessions"]}
