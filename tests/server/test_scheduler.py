"""The scheduler on its own threads: frames never wait for renders, work before the viewer's pictures,
sessions in turn, a session's frames one at a time in order, limits per session and kind, a newer
viewer picture replacing a waiting one, the viewer's pause while frames are held, frames decoded on
their own workers beside the folds, the ingest and render workers' lower OS priorities, and the
background solves: their own lowest lane, a session's one at a time, none while its frames wait.

Each test holds a worker inside a job (a `threading.Event`) to line jobs up behind it, so the order
asserted is the scheduler's choice, never a matter of timing. The viewer's pause is a time: it is
asserted as at least its length, and as far below it without frames."""

from __future__ import annotations

import asyncio
import os
import threading
import time

import pytest

from server.scheduler import (INGEST_NICE, RENDER_NICE, SOLVE_NICE, VIEWER_PAUSE, VIEWER_TURN, ClientGone, Kind,
                              QueueFull, Scheduler, Superseded)

WAIT_S = 30.0


class Gate:
    """A job that records that it started, then waits until the test opens it."""

    def __init__(self):
        self.started, self.opened = threading.Event(), threading.Event()

    def __call__(self, name: str = "gate") -> str:
        self.started.set()
        assert self.opened.wait(WAIT_S), "the test never opened the gate"
        return name

    async def until_started(self) -> None:
        assert await asyncio.to_thread(self.started.wait, WAIT_S), "the gated job never started"


def run(coro_fn, **settings):
    """``coro_fn(scheduler)`` on a fresh scheduler (one worker per lane, limit 8 unless given)."""
    scheduler = Scheduler(**{"frame_workers": 1, "render_workers": 1, "queue_limit": 8, **settings})

    async def main():
        return await asyncio.wait_for(coro_fn(scheduler), WAIT_S)

    try:
        return asyncio.run(main())
    finally:
        scheduler.close()


async def held(s: Scheduler, kind: Kind = "work", session: str = "a", name: str = "gate") -> tuple[Gate, asyncio.Future]:
    """A gated ``kind`` job taken by a worker: with one worker a lane, that lane is busy until the gate opens."""
    gate = Gate()
    job = asyncio.ensure_future(s.run(gate, name, kind=kind, session=session))
    await gate.until_started()
    return gate, job


async def queued(scheduler: Scheduler, count: int) -> None:
    """Let ``count`` submitted jobs reach their queues (each `run` enqueues before its first await)."""
    while scheduler.active < count:
        await asyncio.sleep(0)


def test_a_frame_runs_while_the_render_workers_are_busy():
    async def body(s: Scheduler):
        gate, render = await held(s, name="render")
        assert await s.run(lambda: "folded", kind="frame", session="b") == "folded"
        assert not render.done()  # the frame did not wait for the render
        gate.opened.set()
        assert await render == "render"

    run(body)


def test_the_next_frame_is_decoded_while_the_fold_before_it_runs():
    async def body(s: Scheduler):
        gate, fold = await held(s, "frame", name="fold")  # the only frame worker is folding
        assert await s.run(lambda: "decoded", kind="ingest", session="a") == "decoded"
        assert not fold.done()  # the decode did not wait for the fold
        gate.opened.set()
        assert await fold == "fold"

    run(body)


def test_work_goes_before_the_viewer_and_sessions_take_turns():
    order: list[str] = []

    async def body(s: Scheduler):
        gate, first = await held(s)
        jobs = [asyncio.ensure_future(s.run(order.append, name, kind=kind, session=session))
                for name, kind, session in [("viewer b", "viewer", "b"), ("a1", "work", "a"), ("a2", "work", "a"),
                                            ("a3", "work", "a"), ("b1", "work", "b")]]
        await queued(s, 6)
        gate.opened.set()
        await asyncio.gather(first, *jobs)

    run(body)
    # a's jobs were queued first, b's one waited for a single turn of a's; the viewer came last
    assert order == ["a1", "b1", "a2", "a3", "viewer b"]


def test_looping_work_leaves_the_viewer_a_turn():
    order: list[str] = []

    async def body(s: Scheduler):
        gate, first = await held(s)
        viewer = asyncio.ensure_future(s.run(order.append, "viewer", kind="viewer", session="a", coalesce="page"))
        works = [asyncio.ensure_future(s.run(order.append, f"w{i}", kind="work", session="a")) for i in range(7)]
        await queued(s, 9)
        gate.opened.set()
        await asyncio.gather(first, viewer, *works)

    run(body, queue_limit=16)
    # the gated job was taken before the viewer's waited; then VIEWER_TURN - 1 work jobs passed it over
    assert order.index("viewer") == VIEWER_TURN - 1 and len(order) == 8


def test_while_frames_are_held_a_viewer_picture_waits_a_multiple_of_the_last_ones_time():
    started: dict[str, float] = {}

    def picture(name: str, seconds: float) -> float:
        started[name] = time.monotonic()
        time.sleep(seconds)
        return time.monotonic()

    async def pair(s: Scheduler, name: str, seconds: float) -> float:
        """Seconds from the end of one picture (``seconds`` long) to the start of the next one."""
        end = await s.run(picture, f"{name} 1", seconds, kind="viewer", session="a", coalesce="page")
        await s.run(picture, f"{name} 2", 0.0, kind="viewer", session="a", coalesce="page")
        return started[f"{name} 2"] - end

    async def body(s: Scheduler):
        quiet = await pair(s, "quiet", 0.5)
        gate, fold = await held(s, "frame", session="b")  # another session's fold runs meanwhile
        streaming = await pair(s, "streaming", 0.5)
        # a picture waiting out the pause starts when the last frame ends, not when the pause does
        end = await s.run(picture, "ended 1", 0.5, kind="viewer", session="a", coalesce="page")
        paused = asyncio.ensure_future(s.run(picture, "ended 2", 0.0, kind="viewer", session="a", coalesce="page"))
        await asyncio.sleep(0.25)
        assert not paused.done()
        gate.opened.set()
        await fold
        await paused
        return quiet, streaming, started["ended 2"] - end

    quiet, streaming, ended = run(body)
    assert streaming >= VIEWER_PAUSE * 0.5  # at least the pause (the picture took at least 0.5 s)
    assert quiet < VIEWER_PAUSE * 0.5 / 2  # no frames held: no pause
    assert ended < VIEWER_PAUSE * 0.5 * 2 / 3  # the frame's end lifted it (at 0.25 s, of 1.5)


class SteppedClock:
    """The scheduler's `time.monotonic`, set by the test; once ``step`` is set, each look at it moves it on."""

    def __init__(self, now: float):
        self.now, self.step = now, 0.0

    def monotonic(self) -> float:
        now = self.now
        self.now += self.step
        return now


def test_a_viewer_pause_that_ends_between_two_looks_at_the_clock_is_not_waited_on_forever(monkeypatch):
    import server.scheduler as scheduler

    clock = SteppedClock(100.0)
    monkeypatch.setattr(scheduler, "time", clock)  # the scheduler's clock only (not asyncio's or threading's)

    def picture() -> None:  # one second long on the scheduler's clock: a pause until 104
        clock.now += 1.0

    async def body(s: Scheduler):
        gate, fold = await held(s, "frame", session="b")
        await s.run(picture, kind="viewer", session="a", coalesce="page")
        second = asyncio.ensure_future(s.run(lambda: "second", kind="viewer", session="a", coalesce="page"))
        await asyncio.sleep(0.2)  # the render worker waits out the pause (3 s on its clock, real seconds)
        assert not second.done()
        # the worker's next look finds 0.2 s of the pause left, the look after it none: it must look
        # again then, not wait for a notification that never comes
        clock.now, clock.step = 103.8, 0.5
        with s._lock:
            s._lane("viewer").ready.notify()
        assert await asyncio.wait_for(second, 2.0) == "second"
        gate.opened.set()
        await fold

    run(body)


def test_a_sessions_frames_run_one_at_a_time_in_order_beside_other_sessions():
    order: list[str] = []

    async def body(s: Scheduler):
        gate, a1 = await held(s, "frame", name="a1")
        a2 = asyncio.ensure_future(s.run(order.append, "a2", kind="frame", session="a"))
        a3 = asyncio.ensure_future(s.run(order.append, "a3", kind="frame", session="a"))
        # the second frame worker skips a's frames (a1 is folding) and takes b's
        await s.run(order.append, "b1", kind="frame", session="b")
        assert not a2.done() and order == ["b1"]
        gate.opened.set()
        await asyncio.gather(a1, a2, a3)

    run(body, frame_workers=2)
    assert order == ["b1", "a2", "a3"]


def test_the_queue_limit_holds_per_session_and_kind():
    async def body(s: Scheduler):
        gate = Gate()
        taken = [asyncio.ensure_future(s.run(gate, kind="work", session="a")) for _ in range(2)]
        await queued(s, 2)
        with pytest.raises(QueueFull, match="queue_limit: session a has 2 work jobs"):
            await s.run(str, kind="work", session="a")
        assert s.active == 2  # the refused job changed nothing
        # other sessions and other kinds of the same session have queues of their own
        assert await s.run(lambda: "b", kind="frame", session="b") == "b"
        assert await s.run(lambda: "a frame", kind="frame", session="a") == "a frame"
        gate.opened.set()
        await asyncio.gather(*taken)
        assert s.active == 0
        assert await s.run(lambda: "again", kind="work", session="a") == "again"

    run(body, queue_limit=2)


def test_a_newer_viewer_picture_replaces_the_waiting_one():
    ran: list[str] = []

    async def body(s: Scheduler):
        gate, first = await held(s)
        old = asyncio.ensure_future(s.run(ran.append, "old", kind="viewer", session="a", coalesce="page 1"))
        other = asyncio.ensure_future(s.run(ran.append, "other page", kind="viewer", session="a", coalesce="page 2"))
        await queued(s, 3)
        new = asyncio.ensure_future(s.run(ran.append, "new", kind="viewer", session="a", coalesce="page 1"))
        with pytest.raises(Superseded):
            await old
        assert s.superseded == 1 and s.active == 3
        gate.opened.set()
        await asyncio.gather(first, other, new)

    run(body)
    assert ran == ["other page", "new"]


def test_a_cancelled_waiting_job_leaves_its_queue():
    async def body(s: Scheduler):
        gate, first = await held(s)
        waiting = asyncio.ensure_future(s.run(pytest.fail, "a cancelled job ran", kind="work", session="a"))
        await queued(s, 2)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        assert s.active == 1
        gate.opened.set()
        await first
        assert await s.run(lambda: "next", kind="work", session="a") == "next"

    run(body)


def test_a_waiting_job_whose_client_left_leaves_its_queue():
    async def body(s: Scheduler):
        gate, first = await held(s)
        left = asyncio.Event()

        async def gone() -> bool:
            return left.is_set()

        waiting = asyncio.ensure_future(s.run(pytest.fail, "a job nobody waits for ran", kind="work", session="a",
                                              gone=gone))
        await queued(s, 2)
        left.set()
        with pytest.raises(ClientGone):
            await waiting  # within a look or two (GONE_CHECK_S)
        assert s.active == 1  # its place is free while the first still runs
        gate.opened.set()
        await first
        assert await s.run(lambda: "next", kind="work", session="a", gone=gone) == "next"  # done at once: no look

    run(body)


def test_errors_reach_the_caller():
    async def body(s: Scheduler):
        with pytest.raises(ValueError, match="width: too wide"):
            await s.run(_raise, ValueError("width: too wide"), kind="work", session="a")
        assert s.active == 0

    run(body)


def _raise(exc: Exception):
    raise exc


def _nice() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


def test_ingest_and_render_workers_run_at_lower_os_priorities():
    async def body(s: Scheduler):
        return (await s.run(_nice, kind="frame", session="a"), await s.run(_nice, kind="ingest", session="a"),
                await s.run(_nice, kind="work", session="a"), await s.run(_nice, kind="viewer", session="a"))

    base = _nice()
    frame, ingest, work, viewer = run(body, render_nice=7, ingest_nice=3)
    assert frame == base and ingest == min(base + 3, 19) and work == viewer == min(base + 7, 19)
    defaults = run(body)  # the decoding a little below the folds, the renders well below the decoding
    assert defaults[1:] == (min(base + INGEST_NICE, 19), min(base + RENDER_NICE, 19), min(base + RENDER_NICE, 19))
    assert 0 < INGEST_NICE < RENDER_NICE < SOLVE_NICE


def test_worker_threads_are_bounded_and_stop_on_close():
    scheduler = Scheduler(frame_workers=2, render_workers=3, queue_limit=8, solve_workers=1, ingest_workers=2)

    async def body():
        await asyncio.gather(*[scheduler.run(str, i, kind=kind, session=f"s{i}")
                               for i, kind in enumerate(["frame", "ingest", "work", "viewer"] * 4)])

    before = threading.active_count()
    asyncio.run(body())
    assert threading.active_count() - before == 8
    scheduler.close()
    assert threading.active_count() == before


def test_background_solves_wait_for_nothing_and_hold_no_render_worker():
    async def body(s: Scheduler):
        gate, done = Gate(), []
        assert s.background(lambda: done.append(gate()), "a")
        await gate.until_started()  # the one solve worker is busy: renders and frames still run
        assert await s.run(str, 1, kind="work", session="a") == "1"
        assert await s.run(str, 2, kind="frame", session="a") == "2"
        gate.opened.set()
        while s.active:
            await asyncio.sleep(0.01)
        return done

    assert run(body) == ["gate"]


def test_a_session_has_one_solve_waiting_none_while_its_frames_wait_and_sessions_take_turns():
    async def body(s: Scheduler):
        order, gate = [], Gate()
        assert s.background(gate, "x")  # holds the solve worker
        await gate.until_started()
        assert s.background(lambda: order.append("a1"), "a") and not s.background(lambda: order.append("a2"), "a")
        assert s.background(lambda: order.append("b1"), "b")
        frame_gate = Gate()
        frame = asyncio.ensure_future(s.run(frame_gate, kind="frame", session="c"))
        await frame_gate.until_started()
        assert s.frames_held("c") == 1 and not s.background(lambda: order.append("c1"), "c")  # its fold queues one after
        frame_gate.opened.set()
        await frame
        assert s.frames_held("c") == 0 and s.background(lambda: order.append("c1"), "c")
        gate.opened.set()
        while s.active:
            await asyncio.sleep(0.01)
        return order

    assert run(body) == ["a1", "b1", "c1"]


def test_a_failed_background_job_is_logged_and_the_lane_goes_on(caplog):
    async def body(s: Scheduler):
        done = []
        assert s.background(lambda: _raise(RuntimeError("solve broke")), "a")
        while s.active:
            await asyncio.sleep(0.01)
        assert s.background(lambda: done.append(1), "a")
        while s.active:
            await asyncio.sleep(0.01)
        return done

    assert run(body) == [1]
    assert "solve job of session a failed" in caplog.text and "solve broke" in caplog.text


def test_solve_workers_run_at_the_lowest_os_priority():
    async def body(s: Scheduler):
        seen = []
        s.background(lambda: seen.append(_nice()), "a")
        while s.active:
            await asyncio.sleep(0.01)
        return seen

    assert run(body) == [min(_nice() + SOLVE_NICE, 19)]
