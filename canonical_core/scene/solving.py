"""The colour solve of a scene off its decode path: whether one is due, and the solve itself.

A service shows the last solution in every render (`Scene.gaussians` with ``colours="last"``) and
runs `solve_colours` elsewhere, when its session has no frame waiting. The solve copies the state
under the scene's lock as a decode does and solves outside both locks, so folds and renders go on
meanwhile; it starts from zero, not from the last solution, so that its answer depends on the
state and the kept views only, not on when earlier solves ran (a restarted session, solved after
the same frames, shows the same colours).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from ..decode import colour_offsets
from .decoding import ColourSolution

if TYPE_CHECKING:
    from .scene import Scene


def colour_solve_due(scene: Scene) -> bool:
    """Whether `solve_colours` would solve: the scene keeps views, and its colour solution (if any) is
    of an earlier state. Read without the scene's lock, so that a caller on an event loop never waits
    for a fold: `solve_colours` checks again under it."""
    solution = scene._decoding.solution
    return len(scene._keyframes) > 0 and (solution is None or solution.frames < scene.frames)


def colours_solved_frames(scene: Scene) -> int | None:
    """The frame count of the state the kept colour solution was solved for; None: none kept (a
    correction's carried solution counts as the older state it is due from)."""
    solution = scene._decoding.solution
    return None if solution is None else max(solution.frames, 0)


def solve_colours(scene: Scene, stop: Callable[[], bool] | None = None) -> bool:
    """Solve the colours of ``scene`` as it is now against its kept views, from zero
    (`decode.colour_offsets`), and keep the solution for its later decodes, which then show it.
    Returns whether one was kept (False: none was due, or a correction replaced the state or a
    newer solution landed meanwhile). ``stop`` is asked between the solve's steps; when it answers
    True the solve raises `decode.SolveStopped` and keeps nothing."""
    decoding = scene._decoding
    with decoding.lock:  # the decode lock before the scene's, as every decode takes them
        with scene._lock:
            if not colour_solve_due(scene):
                return False
            work = decoding.take(scene._decode_inputs(live=True), features=False)
        base, epoch = decoding.base(work), decoding.epoch
    offsets = colour_offsets(base, work.views, stop=stop)  # seconds of work: no lock held
    with decoding.lock:
        if not decoding.land(ColourSolution(work.chosen.rows, offsets, work.frames), epoch):
            return False
        with scene._lock:
            decoding.forget()  # the kept Gaussians show the last solution
    return True
