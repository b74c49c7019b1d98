"""The colour solve off the decode path (`Scene.solve_colours`, ``colours="last"``), and the default
that turns the solve on: solutions equal the reference solve of the same state and views."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.decode import SolveStopped
from canonical_core.frame import resize_frame
from canonical_core.scene import Scene
from canonical_core.scene.decoding import ColourSolution

from ..conftest import solved_as_kept

VOXEL = 0.008


@pytest.fixture(scope="module")
def small(shelf_frames):
    return [resize_frame(f, 0.25) for f in shelf_frames[0:20:5]]  # 4 frames, 160x120


def folded(frames, undo_depth: int = 0, **settings) -> Scene:
    scene = Scene(SceneConfig(voxel_size=VOXEL, **settings), undo_depth=undo_depth)
    for f in frames:
        scene.fold(f)
    return scene


def reference(scene: Scene, frames) -> torch.Tensor:  # [N, 16, 3]: the solve of the same fused state, unsolved
    return solved_as_kept(folded(frames, colour_solve={"views": 0}).decode(), scene._keyframes.frames()).sh


@pytest.mark.realdata
def test_the_colour_solve_is_on_by_default_and_decodes_equal_the_reference_solve(small):
    scene = folded(small)
    assert scene.config.colour_solve.views == 16 and len(scene._keyframes) == len(small)
    assert torch.equal(scene.decode().sh, reference(scene, small))


@pytest.mark.realdata
def test_colours_last_shows_the_last_solution_and_solve_colours_makes_the_next_from_zero(small):
    scene = folded(small[:2], colour_solve={"scale": 1.0, "refresh": 1})
    unsolved = folded(small[:2], colour_solve={"views": 0}).decode()
    assert scene.colour_solve_due() and torch.equal(scene.gaussians(colours="last").sh, unsolved.sh)
    digest = scene.digest()
    assert scene.solve_colours() and scene._decoding.solution.frames == 2
    assert scene.digest() == digest  # the fused state is not the solve's
    assert not scene.colour_solve_due() and not scene.solve_colours()
    assert torch.equal(scene.gaussians(colours="last").sh, reference(scene, small[:2]))  # the kept Gaussians went
    first = scene._decoding.solution
    scene.fold(small[2])
    shown = scene.gaussians(colours="last")  # the last solution, on the rows it solved: never a solve in the call
    assert scene._decoding.solution is first and scene.colour_solve_due()
    assert not torch.equal(shown.sh, reference(scene, small[:3]))
    assert scene.solve_colours()  # from zero, not from the last solution: the reference solve of this state
    assert torch.equal(scene.gaussians(colours="last").sh, reference(scene, small[:3]))
    with pytest.raises(ValueError, match="^colours: "):
        scene.gaussians(colours="solved")


@pytest.mark.realdata
def test_a_solve_does_not_depend_on_when_earlier_solves_ran(small):
    often = folded(small[:1])
    for f in small[1:]:
        often.solve_colours()
        often.fold(f)
    often.solve_colours()
    once = folded(small)
    once.solve_colours()
    assert once.digest() == often.digest()
    assert torch.equal(once.gaussians(colours="last").sh, often.gaussians(colours="last").sh)


@pytest.mark.realdata
def test_folds_go_on_while_a_solve_runs_and_a_replaced_state_keeps_no_solution(small):
    scene = folded(small[:2], undo_depth=2)
    solver = threading.Thread(target=scene.solve_colours)
    solver.start()
    scene.fold(small[2])  # takes the scene's lock only: the solve holds it just to copy the state
    solver.join()
    assert scene.digest() == folded(small[:3]).digest()  # the frame folded as without a solve
    assert scene._decoding.solution.frames in (2, 3) and scene.frames == 3
    epoch = scene._decoding.epoch  # a solve that copied this state ...
    scene.rollback(2)  # ... lands after a correction replaced it: not kept
    carried = scene._decoding.solution
    late = ColourSolution(np.arange(3, dtype=np.int64), torch.zeros(3, 4, 3), 3)
    with scene._decoding.lock:
        assert not scene._decoding.land(late, epoch)
    assert scene._decoding.solution is carried


@pytest.mark.realdata
def test_a_stopped_solve_keeps_nothing_and_the_next_one_solves(small):
    scene = folded(small[:2])
    with pytest.raises(SolveStopped):
        scene.solve_colours(stop=lambda: True)
    assert scene._decoding.solution is None and scene.colour_solve_due()
    assert scene.solve_colours(stop=lambda: False)
    assert torch.equal(scene.gaussians(colours="last").sh, reference(scene, small[:2]))
