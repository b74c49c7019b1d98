"""The sessions' colour solves, in the background: queued when a session has no frame waiting.

Renders show a session's last colour solution and never solve (`Session.gaussians`). After each
fold, and after each render, `solve_soon` queues a solve of the session on the scheduler's lowest
lane (`Scheduler.background`) when its solution is of an earlier state and no frame of it is
running or waiting; a solve that finds a frame waiting when its turn comes leaves it to that
frame's fold. A solve that lands queues the next if frames were folded while it ran, so a stream
that pauses is shown in solved colours one or two solves after its last frame. The solve copies the
session's state as a decode does and solves outside its locks (`Scene.solve_colours`): a frame that
arrives meanwhile folds at once, and the solve gives up at its next step, so that it takes neither
cores nor the interpreter's lock from a stream (the frame's fold queues a new one once no frame
waits). A solve begins only after `QUIET_S` without a new frame: between two frames of a stream
there is no time to solve, and its first step, a copy and decode of the state, would be spent for
nothing.
"""

from __future__ import annotations

import functools
import weakref

import time

from .memory import release_memory
from .scheduler import Scheduler
from .session import Session

# seconds a session's state must stay as it is before its solve begins: longer than the gap between
# two frames of any stream worth the name, short against the second or two a solve takes
QUIET_S = 0.25


def solve_soon(jobs: Scheduler, session: Session) -> bool:
    """Queue a background colour solve of ``session`` if one is due and none waits; returns whether
    one was queued. The job refers to the session weakly, so a deleted session's memory is not held by
    a solve that waits for its turn."""
    return session.colour_solve_due() and jobs.background(functools.partial(_solve, jobs, weakref.ref(session)), session.id)


def _solve(jobs: Scheduler, ref: weakref.ref) -> None:
    session = ref()
    if session is None:
        return
    frames = session.scene.frames

    def stop() -> bool:  # a frame on its way, or one folded since: its fold queues the next solve
        return session.deleted or jobs.frames_held(session.id) > 0 or session.scene.frames != frames

    solved = False
    if not stop():
        time.sleep(QUIET_S)
        if not stop():  # else a stream: no time to solve between its frames
            solved = session.solve_colours(stop)
    if session.deleted:
        # deleted while this job held it (asleep or solving): what it held goes back now, not at the
        # next cycle collection (the delete's own release found it still held)
        del session
        release_memory()
    elif solved:
        solve_soon(jobs, session)  # frames folded while it solved: their colours are due too
