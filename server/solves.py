"""The sessions' colour solves, in the background: queued when a session has no frame waiting.

Renders show a session's last colour solution and never solve (`Session.gaussians`). After each
fold, and after each render, `solve_soon` queues a solve of the session on the scheduler's lowest
lane (`Scheduler.background`) when its solution is of an earlier state and no frame of it is
running or waiting; a solve that finds a frame waiting when its turn comes leaves it to that
frame's fold. A solve that lands queues the next if frames were folded while it ran, so a stream
that pauses is shown in solved colours one or two solves after its last frame. The solve copies the
session's state as a decode does and solves outside its locks (`Scene.solve_colours`): a frame that
arrives meanwhile folds at once.
"""

from __future__ import annotations

import functools
import weakref

from .memory import release_memory
from .scheduler import Scheduler
from .session import Session


def solve_soon(jobs: Scheduler, session: Session) -> bool:
    """Queue a background colour solve of ``session`` if one is due and none waits; returns whether
    one was queued. The job refers to the session weakly, so a deleted session's memory is not held by
    a solve that waits for its turn."""
    return session.colour_solve_due() and jobs.background(functools.partial(_solve, jobs, weakref.ref(session)), session.id)


def _solve(jobs: Scheduler, ref: weakref.ref) -> None:
    session = ref()
    if session is None or jobs.frames_held(session.id) or session.deleted:  # a frame's fold queues the next solve
        return
    solved = session.solve_colours()
    if session.deleted:  # deleted while it solved: what it and its copy of the state held goes back now
        del session
        release_memory()
    elif solved:
        solve_soon(jobs, session)  # frames folded while it solved: their colours are due too
