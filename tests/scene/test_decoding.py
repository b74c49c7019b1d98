"""The colour solution a scene keeps (`scene.decoding.ColourSolution`): int32 rows and float16 offsets,
rounded where a solve lands, so that a solution fresh from a solve and one read back from a snapshot
give the same Gaussians bit for bit; snapshots that kept it wider (int64 rows, float32 offsets) load."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.decode import with_colour_offsets
from canonical_core.frame import resize_frame
from canonical_core.scene import Scene
from canonical_core.scene.decoding import ColourSolution

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"


def assert_equal_gaussians(a, b):
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_a_solution_is_kept_narrow_whatever_it_is_made_of():
    offsets = torch.linspace(-1.3, 1.7, 3 * 4 * 3).reshape(3, 4, 3)  # float32, as a solve answers
    solution = ColourSolution(np.array([2, 5, 9], np.int64), offsets, 7)
    assert solution.rows.dtype == np.int32 and solution.offsets.dtype == torch.float16
    assert not torch.equal(solution.offsets.float(), offsets)  # rounded: these are not float16 values
    assert solution.nbytes() == 3 * 4 + offsets.numel() * 2
    shown = solution.at(np.array([0, 5, 9], np.int64))  # a row it did not solve gets no offset
    assert shown.dtype == torch.float32 and not shown[0].any() and torch.equal(shown[1:], offsets[1:].half().float())


@pytest.fixture(scope="module")
def small(shelf_frames):
    return [resize_frame(f, 0.25) for f in shelf_frames[0:20:5]]  # 4 frames, 160x120


@pytest.mark.realdata
@pytest.mark.parametrize("solve", ["decode", "background"])  # a decode that solves, or `Scene.solve_colours`
def test_a_solution_fresh_from_a_solve_and_read_back_from_a_snapshot_give_the_same_gaussians(small, solve, tmp_path):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0}))
    for f in small[:3]:
        scene.fold(f)
    if solve == "decode":
        fresh = scene.decode()
    else:
        assert scene.solve_colours()
        fresh = scene.gaussians(colours="last")
    solution = scene._decoding.solution
    assert solution.frames == 3 and solution.rows.dtype == np.int32 and solution.offsets.dtype == torch.float16
    scene.save(tmp_path / "scene.cgs")
    loaded = Scene.load(tmp_path / "scene.cgs")
    read = loaded._decoding.solution
    assert np.array_equal(read.rows, solution.rows) and torch.equal(read.offsets, solution.offsets)
    assert_equal_gaussians(loaded.gaussians(colours="last"), fresh)
    assert_equal_gaussians(loaded.decode(), fresh)  # not due for a solve: the decode shows the kept one


def test_a_snapshot_that_kept_the_solution_wider_loads_it_narrowed():
    """tests/fixtures/scene_v5_solved.snap: written by the code that kept int64 rows and float32 offsets."""
    path = FIXTURES / "scene_v5_solved.snap"
    with np.load(path) as stored:
        rows, offsets = stored["colour_solution.rows"], stored["colour_solution.offsets"]
    assert rows.dtype == np.int64 and offsets.dtype == np.float32
    scene = Scene.load(path)
    solution = scene._decoding.solution
    assert solution.frames == scene.frames and np.array_equal(solution.rows, rows)
    assert torch.equal(solution.offsets, torch.from_numpy(offsets).half())
    unsolved = scene.decode_from(scene.decode_inputs()._replace(views=[]))
    assert len(unsolved) == len(rows)  # the state it was solved for: the same rows decode
    assert torch.equal(scene.gaussians(colours="last").sh, with_colour_offsets(unsolved, solution.offsets).sh)
    again = Scene.from_bytes(scene.to_bytes())  # written narrow now, read back the same
    assert np.array_equal(again._decoding.solution.rows, solution.rows)
    assert torch.equal(again._decoding.solution.offsets, solution.offsets)


@pytest.fixture(scope="module")
def folded():
    from canonical_core.datasets import synthetic_rgbd

    scene = Scene(SceneConfig(voxel_size=0.02))
    scene.fold(synthetic_rgbd(num_frames=1, width=64, height=48)[0])
    return scene


BAD_DECODE_ARGUMENTS = [
    (dict(max_gaussians=1.5), r"^max_gaussians: expected a non-negative integer or None, got 1\.5$"),
    (dict(max_gaussians="10"), r"^max_gaussians: expected a non-negative integer or None, got '10'$"),
    (dict(max_gaussians=True), r"^max_gaussians: .*got True$"),
    (dict(max_gaussians=-1), r"^max_gaussians: .*got -1$"),
    (dict(min_support=float("nan")), r"^min_support: expected >= 0 \(a number\), got nan$"),
    (dict(min_support="0.5"), r"^min_support: expected >= 0 \(a number\), got '0.5'$"),
]


@pytest.mark.parametrize("kwargs, message", BAD_DECODE_ARGUMENTS)
def test_bad_decode_arguments_are_refused_naming_them(folded, kwargs, message):
    digest = folded.digest()
    with pytest.raises(ValueError, match=message):
        folded.decode(**kwargs)
    assert folded.digest() == digest


LEVELS_OF_DETAIL = [(kwargs, message) for kwargs, message in BAD_DECODE_ARGUMENTS if "max_gaussians" in kwargs]


@pytest.mark.parametrize("kwargs, message", LEVELS_OF_DETAIL)
def test_a_bad_level_of_detail_is_refused_by_gaussians_too(folded, kwargs, message):
    with pytest.raises(ValueError, match=message):
        folded.gaussians(**kwargs)


def test_decode_takes_numpy_integers_and_an_infinite_support_floor(folded):
    assert len(folded.decode(max_gaussians=np.int64(10))) == 10
    assert len(folded.decode(min_support=np.float32(0.0))) == len(folded.decode())
    assert len(folded.decode(min_support=float("inf"))) == 0  # no voxel has more support than that
