"""The background colour solve's hold on a session: a session deleted while its solve job holds it
(waiting out the quiet time, or solving) goes back to the system when the job ends, not at some later
garbage collection (a session and its snapshots and corrections refer to each other, so only the
cycle collector frees one)."""

from __future__ import annotations

import gc
import time
import weakref

import pytest

from canonical_core import SceneConfig
from server import solves, wire
from server.scheduler import Scheduler
from server.store import SessionStore

from .harness import VOXEL, msgpack_frame

pytestmark = pytest.mark.realdata

WAIT_S = 30.0


def until(condition, timeout: float = WAIT_S) -> bool:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def test_a_session_deleted_while_its_solve_waits_out_the_quiet_time_is_freed_when_the_solve_ends(
        tmp_path, frames, monkeypatch):
    # a long quiet time, so that the delete surely lands while the job holds the session asleep
    monkeypatch.setattr(solves, "QUIET_S", 2.0)
    store = SessionStore(tmp_path, max_sessions=2)
    store.open()
    jobs = Scheduler(frame_workers=1, render_workers=1, queue_limit=8)
    gc.disable()  # only the job's own release may free the session: no collection happens by chance
    try:
        session = store.create(SceneConfig(voxel_size=VOXEL))
        payload = wire.pack(msgpack_frame(frames[0]))
        session.add_frame(payload, wire.frame_from_message(wire.unpack(payload)), 10**6, 1e9)
        assert solves.solve_soon(jobs, session)
        assert until(lambda: jobs.background_running == 1)
        freed = weakref.ref(session)
        assert store.delete(session.id)
        del session
        assert freed() is not None  # the job holds it while it waits out the quiet time
        assert until(lambda: jobs.background_done == 1)
        assert freed() is None
    finally:
        gc.enable()
        jobs.close()
        store.close()
