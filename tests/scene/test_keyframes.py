"""Keyframes for the colour solve: eviction keeps the stream spread; the scene decodes with them
as `solve_colours` does (its offsets kept in float16), and they travel with the snapshot."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.decode import colour_offsets, with_colour_offsets
from canonical_core.frame import resize_frame
from canonical_core.scene import Scene
from canonical_core.scene.decoding import REFRESH_ITERATIONS
from canonical_core.scene.selection import decoded_rows
from canonical_core.scene.keyframes import Keyframes

from ..conftest import make_frame, solved_as_kept
from ..datasets.conftest import slambook_path  # noqa: F401 (a fixture)


def test_eviction_keeps_the_ends_and_an_even_spread():
    keyframes = Keyframes(capacity=5)
    frame = make_frame(np.ones((4, 4), np.float32))
    for index in range(41):
        keyframes.add(index, frame)
    assert keyframes.indices[0] == 0 and keyframes.indices[-1] == 40 and len(keyframes) == 5
    gaps = np.diff(keyframes.indices)
    assert gaps.max() <= 2 * gaps.min()  # 41 frames into 5: gaps near 10 each


def test_capacity_one_keeps_the_newest_and_zero_keeps_nothing():
    frame = make_frame(np.ones((4, 4), np.float32))
    one, none = Keyframes(1), Keyframes(0)
    for index in range(3):
        one.add(index, frame)
        none.add(index, frame)
    assert one.indices == [2] and len(none) == 0 and none.nbytes() == 0


def test_keyframes_hold_colour_and_camera_only():
    keyframes = Keyframes(2)
    keyframes.add(0, make_frame(np.ones((4, 4), np.float32), features=np.ones((4, 4, 3), np.float32)))
    (kept,) = keyframes.frames()
    assert kept.depth is None and kept.features is None and kept.rgb.shape == (4, 4, 3)


@pytest.mark.parametrize("capacity", [-1, 2.0, True])
def test_bad_capacity_names_the_field(capacity):
    with pytest.raises(ValueError, match="capacity"):
        Keyframes(capacity)


@pytest.mark.parametrize("setting, value", [("views", -1), ("views", 65), ("views", 1.5), ("scale", 0.0),
                                            ("scale", 1.5), ("scale", True)])
def test_scene_config_checks_the_colour_solve_settings(setting, value):
    with pytest.raises(ValueError, match=rf"^colour_solve\.{setting}: "):
        SceneConfig(voxel_size=0.01, colour_solve={setting: value})


@pytest.mark.realdata
def test_keyframes_are_kept_at_their_scale(shelf_frames):
    keyframes = Keyframes(2, scale=0.5)
    keyframes.add(0, shelf_frames[0])
    (kept,) = keyframes.frames()
    assert kept.rgb.shape == (240, 320, 3) and kept.camera.width == 320
    assert kept.camera.fx == pytest.approx(shelf_frames[0].camera.fx / 2)
    with pytest.raises(ValueError, match="scale"):
        Keyframes(2, scale=0.0)


@pytest.fixture(scope="module")
def small(shelf_frames):
    return [resize_frame(f, 0.25) for f in shelf_frames[0:20:5]]  # 4 frames, 160x120


@pytest.mark.realdata
def test_decode_solves_colours_against_the_kept_views(small):
    solving = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0}))
    plain = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 0}))
    for f in small:
        solving.fold(f)
        plain.fold(f)
    kept = solving._keyframes.frames()
    assert [k.frame_id for k in kept] == [small[i].frame_id for i in (0, 2, 3)]
    expected, got = solved_as_kept(plain.decode(), kept), solving.decode()
    for name in ("means", "opacities", "sh"):
        assert torch.equal(getattr(expected, name), getattr(got, name)), name
    assert not torch.equal(plain.decode().sh, got.sh)
    solution = solving._decoding.solution  # kept: later decodes start from it
    assert solution.frames == 4 and np.array_equal(solution.rows, np.sort(solution.rows)) and len(solution.rows) == len(got)
    assert solving.memory_bytes() == plain.memory_bytes() + sum(k.rgb.numel() for k in kept) + solution.nbytes()


@pytest.mark.realdata
def test_decode_inputs_are_a_copy_that_later_folds_leave_alone(small):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 2, "scale": 1.0}))
    for f in small[:3]:
        scene.fold(f)
    inputs, before = scene.decode_inputs(), scene.decode()
    assert [v.frame_id for v in inputs.views] == [small[0].frame_id, small[2].frame_id]
    scene.fold(small[3])  # adds voxels, changes sums and evicts a kept view
    later = scene.decode_from(inputs)
    for name in ("means", "scales", "opacities", "sh"):
        assert torch.equal(getattr(later, name), getattr(before, name)), name
    assert len(scene.decode()) != len(later)
    with pytest.raises(ValueError, match="max_gaussians"):
        scene.decode_from(inputs, max_gaussians=-1)


@pytest.mark.realdata
def test_keyframes_travel_with_the_snapshot(small, tmp_path):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 8}))
    for f in small[:2]:
        scene.fold(f)
    scene.save(tmp_path / "scene.cgs")
    loaded = Scene.load(tmp_path / "scene.cgs")
    assert loaded.digest() == scene.digest() and loaded._keyframes.indices == [0, 1]
    assert loaded._keyframes.frames()[0].rgb.shape == (60, 80, 3)  # kept at half size
    assert torch.equal(loaded.decode().sh, scene.decode().sh)
    for f in small[2:]:  # resumed folding keeps views as the uninterrupted scene does
        scene.fold(f)
        loaded.fold(f)
    assert loaded.digest() == scene.digest()


@pytest.mark.realdata
def test_a_frame_that_fails_to_fold_is_not_kept(small):
    probe = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 0}))
    probe.fold(small[0])
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 8}, max_voxels=len(probe) + 10))
    scene.fold(small[0])
    with pytest.raises(ValueError, match="max_voxels"):  # the second frame would need more voxels
        scene.fold(small[3])
    assert scene._keyframes.indices == [0]


def rows_of(scene: Scene) -> np.ndarray:  # the voxel rows a full decode of the scene turns into Gaussians
    return decoded_rows(scene.decode_inputs().sums, 0.0, scene.config).rows


@pytest.mark.realdata
def test_decodes_reuse_the_solution_until_refresh_frames_were_folded(small):
    solving = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0, "refresh": 2}))
    plain = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 0}))
    for f in small[:2]:
        solving.fold(f)
        plain.fold(f)
    solving.decode()
    first = solving._decoding.solution
    assert first.frames == 2
    solving.fold(small[2])
    plain.fold(small[2])
    got, base, rows = solving.decode(), plain.decode(), rows_of(solving)
    assert solving._decoding.solution is first  # one frame since: the same solution, on the rows it solved
    assert torch.equal(got.sh, with_colour_offsets(base, first.at(rows)).sh)
    new = ~np.isin(rows, first.rows)
    assert new.sum() > 100 and torch.equal(got.sh[torch.from_numpy(new)], base.sh[torch.from_numpy(new)])
    solving.fold(small[3])  # two frames since: solved again, from the last solution
    plain.fold(small[3])
    got, base, rows = solving.decode(), plain.decode(), rows_of(solving)
    second = solving._decoding.solution
    assert second.frames == 4 and np.array_equal(second.rows, rows)
    expected = colour_offsets(base, solving._keyframes.frames(), first.at(rows), iterations=REFRESH_ITERATIONS).half()
    assert torch.equal(second.offsets, expected) and torch.equal(got.sh, with_colour_offsets(base, expected).sh)


@pytest.mark.realdata
def test_a_partial_decode_leaves_the_solution_alone(small):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0, "refresh": 1}))
    scene.fold(small[0])
    scene.decode()
    solution = scene._decoding.solution
    scene.fold(small[1])  # a solve is due, but a level of detail or a support floor does not replace it
    assert len(scene.decode(max_gaussians=200)) == 200 and len(scene.decode(min_support=1.0)) > 0
    assert scene._decoding.solution is solution
    scene.decode()
    assert scene._decoding.solution.frames == 2


@pytest.mark.realdata
def test_the_solution_travels_with_the_snapshot_and_stays_out_of_the_digest(small, tmp_path):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0, "refresh": 4}),
                  undo_depth=2)
    for f in small[:2]:
        scene.fold(f)
    digest = scene.digest()
    scene.decode()
    assert scene.digest() == digest
    scene.fold(small[2])  # the stored solution is a frame old: a restored scene must reuse it, not solve afresh
    scene.save(tmp_path / "scene.cgs")
    loaded = Scene.load(tmp_path / "scene.cgs")
    assert loaded._decoding.solution.frames == 2 and np.array_equal(loaded._decoding.solution.rows, scene._decoding.solution.rows)
    assert torch.equal(loaded.decode().sh, scene.decode().sh)
    plain = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 0}))
    for f in small[:3]:
        plain.fold(f)
    assert not torch.equal(loaded.decode().sh, solved_as_kept(plain.decode(), loaded._keyframes.frames()).sh)
    solved = scene._decoding.solution
    scene.rollback(2)  # the solution stays on the voxels that are still there, due for a re-solve
    carried = scene._decoding.solution
    assert carried.frames == 2 - scene.config.colour_solve.refresh
    assert np.array_equal(carried.rows, solved.rows[solved.rows < len(scene)])
    assert torch.equal(carried.offsets, solved.offsets[torch.from_numpy(solved.rows < len(scene))])


@pytest.mark.realdata
@pytest.mark.parametrize("undo_depth", [0, 4])  # re-folded from the start (no undo records), or rolled back in place
def test_a_correction_carries_the_solution_by_voxel_key_and_the_next_decode_re_solves(small, undo_depth):
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 3, "scale": 1.0}), keep_frames=True,
                  undo_depth=undo_depth)
    for f in small:
        scene.fold(f)
    scene.decode()
    before = scene._decoding.solution
    offsets_of = dict(zip(scene._voxels.state["keys"][before.rows].tolist(), before.offsets))
    pose = small[3].camera.c2w64().copy()
    pose[0, 3] += 0.01
    scene.update_poses({small[3].frame_id: pose})
    carried = scene._decoding.solution  # on the re-folded map's rows: each voxel key keeps its offsets
    assert carried.frames == scene.frames - scene.config.colour_solve.refresh
    keys = scene._voxels.state["keys"][carried.rows]
    assert np.array_equal(carried.rows, np.sort(carried.rows)) and len(carried.rows) > 0.8 * len(before.rows)
    assert all(torch.equal(offset, offsets_of[key]) for key, offset in zip(keys.tolist(), carried.offsets))
    base, rows = scene.decode_from(scene.decode_inputs()._replace(views=[])), rows_of(scene)
    expected = colour_offsets(base, scene._keyframes.frames(), carried.at(rows), iterations=REFRESH_ITERATIONS).half()
    scene.decode()  # due: re-solved from the carried offsets, not from zero
    assert scene._decoding.solution.frames == scene.frames and torch.equal(scene._decoding.solution.offsets, expected)


def test_a_kept_view_leaves_out_the_fill_at_its_edges_and_keeps_its_geometry():
    """A colour image warped onto the depth camera is padded at its edges with one colour where no
    depth is (`fill_margins`): the kept view is cropped to the rest, its principal point moved with it,
    so that a world point projects to the same place of the picture; no crop without depth."""
    from canonical_core import Frame
    from canonical_core.scene.keyframes import fill_margins, kept_view

    from canonical_core.camera import Camera

    frame = Frame(rgb=np.zeros((40, 48, 3), np.uint8), camera=Camera([[40, 0, 23.5], [0, 40, 19.5], [0, 0, 1]], np.eye(4), 48, 40))
    rgb = np.random.default_rng(0).integers(0, 255, (40, 48, 3)).astype(np.uint8)
    rgb[:3], rgb[:, -5:] = 255, 255  # a white fill on two sides
    depth = np.ones((40, 48), np.float32)
    depth[:3], depth[:, -5:] = 0.0, 0.0
    padded = Frame(rgb=rgb, camera=frame.camera, depth=depth)
    assert fill_margins(padded) == (3, 0, 0, 5)
    view = kept_view(padded, 1.0)
    assert view.rgb.shape == (37, 43, 3) and torch.equal(view.rgb, torch.from_numpy(rgb[3:, :43]))
    point = frame.camera.lift(torch.tensor([[20.0, 17.0]]), torch.tensor([1.0]))
    uv_full, _ = frame.camera.project(point)
    uv_kept, _ = view.camera.project(point)
    assert torch.allclose(uv_kept, uv_full - torch.tensor([0.0, 3.0]), atol=1e-4)
    depth[:3, :43] = 1.0  # depth in the white rows: they show something
    assert fill_margins(Frame(rgb=rgb, camera=frame.camera, depth=depth)) == (0, 0, 0, 5)
    assert fill_margins(Frame(rgb=rgb, camera=frame.camera)) == (0, 0, 0, 0)


@pytest.mark.realdata
def test_the_colour_solve_paints_no_outline_of_the_kept_views_white_borders(slambook_path):
    """slambook's colour frames carry a white border where the registered depth has none: solved
    colours fitted to it drew each kept view's outline into the scene as white lines; without it, the
    solve draws about as few white pixels as the fused colours and improves on them inside the border."""
    from canonical_core import render
    from canonical_core.datasets import load_tum

    frames = list(load_tum(slambook_path, K=(518.0, 519.0, 325.5, 253.5)))
    white, inner = {}, {}
    for views in (16, 0):
        scene = Scene(SceneConfig(colour_solve={"views": views}))
        for f in frames:
            scene.fold(f)
        r = (render(scene.gaussians(), frames[2].camera, colour="normalised").rgb.clamp(0, 1) * 255).round().numpy()
        gt = frames[2].rgb.numpy().astype(np.float64)
        luma = lambda x: x @ np.array([0.299, 0.587, 0.114])  # noqa: E731
        white[views] = int(((luma(r) - luma(gt) > 60) & (np.ptp(r, axis=-1) < 40) & (luma(r) > 140)).sum())
        inside = (slice(6, -6), slice(8, -8))  # within the border
        inner[views] = 10 * np.log10(255**2 / ((r[inside] - gt[inside]) ** 2).mean())
    assert white[16] < 1.5 * white[0] + 50, white
    assert inner[16] > inner[0], inner
