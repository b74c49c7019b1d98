"""Decodes after a fold reuse what earlier decodes made of the voxels the fold left alone, and are the
same as a decode from scratch (`Scene.decode_from`, `scene.decoded.DecodedRows`)."""

import dataclasses
import threading

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.scene import Scene
from canonical_core.decode import support_unit
from canonical_core.scene.decoded import HALF_PARTS, PARTS, DecodedRows, gather_rows
from canonical_core.scene.decoding import DECODE_CACHE_ENTRIES
from canonical_core.scene.selection import decoded_rows, scene_features
from canonical_core.scene.fields import fields_from_sums
from canonical_core.scene import stamps as stamp_clock
from canonical_core.scene.stamps import STAMP_LIMIT, StampClock
from ..conftest import folded_scene as _folded_scene, make_frame

UNSOLVED = {"views": 0}  # the decoded rows are under test: the colour solve off, whose solutions vary by decode history


def folded_scene(frames, voxel_size: float = 0.008, **settings):
    return _folded_scene(frames, voxel_size, colour_solve=UNSOLVED, **settings)


def assert_same_gaussians(a, b):
    for name in ("opacities", "features", *PARTS):
        x, y = getattr(a, name), getattr(b, name)
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        assert x.shape == y.shape, name
        assert torch.allclose(x, y, rtol=1e-5, atol=1e-6), (name, (x - y).abs().max())


def from_scratch(scene: Scene, inputs=None, **kwargs):
    """The decode without reuse: the same inputs without their fold stamps."""
    inputs = scene.decode_inputs() if inputs is None else inputs
    return scene.decode_from(inputs._replace(changed_at=None), **kwargs)


def decoded_row_counts(scene: Scene) -> list[int]:
    """Record how many voxels each decode of ``scene`` runs through the decoder (the real one)."""
    counts, decode = [], scene.decoder.shapes_and_colours

    def recording(fields, voxel_size, base=None):
        counts.append(len(fields["features"]))
        return decode(fields, voxel_size, base)

    scene.decoder.shapes_and_colours = recording
    return counts


@pytest.fixture(scope="module")
def shelf(shelf_frames):
    return [dataclasses.replace(f) for f in shelf_frames[:6]]


@pytest.mark.realdata
def test_a_decode_after_a_fold_decodes_only_what_the_fold_touched_and_equals_a_fresh_decode(shelf):
    scene = folded_scene(shelf[:4])
    counts = decoded_row_counts(scene)
    first = scene.decode()
    assert counts == [len(first)]  # nothing to reuse yet
    assert_same_gaussians(scene.decode(), first)  # unchanged scene: every voxel reused
    assert counts[-1] == 0
    report = scene.fold(shelf[4])
    touched = report.new_voxels + report.updated_voxels
    after = scene.decode()
    assert 0 < counts[-1] <= touched < len(after)
    assert_same_gaussians(after, from_scratch(scene))
    # a subset (level of detail, a support floor) reuses the same rows
    for kwargs in ({"max_gaussians": 5000}, {"min_support": 0.5}):
        subset = scene.decode(**kwargs)
        assert counts[-1] == 0
        assert_same_gaussians(subset, from_scratch(scene, **kwargs))


@pytest.mark.realdata
def test_decode_inputs_taken_before_later_folds_still_decode_their_own_state(shelf):
    scene = folded_scene(shelf[:3])
    early = scene.decode_inputs()
    scene.fold(shelf[3])
    scene.decode()  # the cache now holds rows of the later state
    assert_same_gaussians(scene.decode_from(early), from_scratch(scene, early))


@pytest.mark.realdata
def test_a_decode_taken_from_the_live_state_keeps_that_state_while_later_folds_change_it(shelf):
    """`Scene.gaussians` reads the state itself under the scene's lock (`SceneDecoding.take`) and
    decodes after releasing it: folds that overwrite the rows it read must not reach its result."""
    scene = folded_scene(shelf[:3])
    scene.gaussians()  # decoded rows to reuse: the work copies sums of the fold's rows, F_scene of the rest
    scene.fold(shelf[3])
    expected = from_scratch(scene)
    with scene._decoding.lock:
        with scene._lock:
            work = scene._decoding.take(scene._decode_inputs(live=True))
        assert 0 < len(work.todo) < len(work.chosen.rows) and work.features is not None
        scene.fold(shelf[4])
        scene.fold(shelf[1])  # seen before: it updates rows the work reuses
        got = scene._decoding.finish(work)
    assert_same_gaussians(got, expected)
    assert_same_gaussians(scene.gaussians(), from_scratch(scene))


@pytest.mark.realdata
def test_a_changed_decoder_parameter_is_not_served_from_earlier_decodes(shelf):
    scene = folded_scene(shelf[:1])
    before = scene.decode()
    with torch.no_grad():
        scene.decoder.offset.bias += torch.tensor([0.25, 0.0, 0.0])  # a quarter voxel along x
    after = scene.decode()
    assert torch.allclose(after.means - before.means, torch.tensor([0.25 * 0.008, 0.0, 0.0]), atol=1e-6)
    assert_same_gaussians(after, from_scratch(scene))
    scene.decoder.min_extent = 0.8  # a clamp, not a parameter
    wider = scene.decode()
    assert wider.scales.max(1).values.min() >= 0.8 * 0.008 * 0.999
    assert_same_gaussians(wider, from_scratch(scene))


@pytest.mark.realdata
def test_one_scenes_inputs_never_match_another_scenes_decoded_rows(shelf):
    a, b = Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.008)), Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.008))
    a.fold(shelf[0])
    b.fold(shelf[5])  # the same number of folds: equal per-scene fold counts would collide
    b.decode()
    inputs = a.decode_inputs()
    assert_same_gaussians(b.decode_from(inputs), from_scratch(a, inputs))


@pytest.mark.realdata
def test_a_loaded_snapshot_decodes_and_folds_on_like_the_original(shelf):
    scene = folded_scene(shelf[:2])
    scene.decode()
    loaded = Scene.from_bytes(scene.to_bytes())
    assert_same_gaussians(loaded.decode(), scene.decode())
    for s in (scene, loaded):
        s.fold(shelf[2])
    assert_same_gaussians(loaded.decode(), scene.decode())
    assert_same_gaussians(loaded.decode(), from_scratch(loaded))


def changed_rows(before: dict, after: dict) -> np.ndarray:  # [V before] bool
    """The rows of ``before`` (`Scene.sums`) whose sums differ in ``after`` (the see-through evidence
    aside: it is no input of a row's decoded shape and colour, and folds change it far and wide)."""
    n = len(before["keys"])
    changed = np.zeros(n, bool)
    for name, column in before.items():
        if name != "free":
            changed |= (after[name][:n] != column).reshape(n, -1).any(1)
    return changed


@pytest.fixture
def clock(monkeypatch) -> StampClock:
    """The process's change-stamp clock, fresh for the test: its next stamp is 1, in epoch 0."""
    fresh = StampClock()
    monkeypatch.setattr(stamp_clock, "STAMPS", fresh)
    return fresh


@pytest.mark.realdata
def test_stamps_past_the_int32_limit_start_an_epoch_in_which_no_stale_decoded_row_is_reused(shelf, clock):
    scene = Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.008), undo_depth=2)
    counts = decoded_row_counts(scene)
    scene.fold(shelf[0])
    scene.decode()  # decoded rows of stamp 1
    clock.last = STAMP_LIMIT - 1
    scene.fold(shelf[1])  # the epoch's last stamp: int32's largest
    changed_at = scene._voxels.changed_at
    assert changed_at.dtype == np.int32 and changed_at.max() == STAMP_LIMIT
    scene.decode()
    sums, stamps = scene.sums(), changed_at[: len(scene)].copy()
    scene.fold(shelf[2])  # the clock wraps: a new epoch, whose first stamp is 1 again
    assert (clock.epoch, clock.last) == (1, 1)
    # rows decoded from sums of stamp 1 whose new sums carry stamp 1 again
    assert (changed_rows(sums, scene.sums()) & (stamps == 1)).sum() > 100
    decoded = scene.decode()
    assert counts[-1] == len(decoded)  # every row kept from the last epoch was stale: decoded afresh
    assert_same_gaussians(decoded, from_scratch(scene))
    scene.rollback(2)  # the rows it restores are restamped in the new epoch; the others are reused
    decoded = scene.decode()
    assert 0 < counts[-1] < len(decoded)
    assert_same_gaussians(decoded, from_scratch(scene))


@pytest.mark.realdata
def test_a_map_restamps_every_voxel_when_it_first_stamps_in_a_new_epoch(shelf, clock):
    """Voxels no fold touched since the last epoch would carry its stamps into the new one, whose
    later folds give the same stamps to other sums: the map's first stamp of the epoch replaces them."""
    clock.last = 2
    scene = folded_scene(shelf[:1])  # stamp 3
    first = scene.sums()
    clock.last = STAMP_LIMIT
    scene.fold(shelf[1])  # a new epoch, stamp 1
    assert clock.epoch == 1 and (scene._voxels.changed_at[: len(scene)] == 1).all()
    scene.fold(shelf[2])  # stamp 2
    scene.decode()
    kept = ~changed_rows(first, scene.sums())  # voxels of the first fold untouched since (stamp 3 without the restamp)
    before = scene.sums()
    scene.fold(shelf[3])  # stamp 3 again
    assert (kept & changed_rows(before, scene.sums())[: len(kept)]).sum() > 100
    assert_same_gaussians(scene.decode(), from_scratch(scene))


def test_labels_arriving_after_a_decode_reach_every_voxel():
    scene = Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.1, free_space={"enabled": False}))
    depth = np.full((4, 4), 1.0)
    scene.fold(make_frame(depth, fx=4.0))
    assert scene.decode().labels is None
    labels = np.zeros((4, 4, 3), np.float32)
    labels[..., 1] = 1.0
    scene.fold(make_frame(depth * 1.5, fx=4.0, labels=labels))  # new voxels with labels, old ones without
    decoded = scene.decode()
    assert decoded.labels is not None and decoded.labels.shape == (len(decoded), 3)
    assert_same_gaussians(decoded, from_scratch(scene))
    assert (decoded.labels[:, 1] > 0.99).sum() > 0 and (decoded.labels.sum(1) == 0).sum() > 0


@pytest.mark.realdata
def test_the_decoded_rows_count_in_the_scenes_memory(shelf):
    scene = folded_scene(shelf[:1])
    before = scene.memory_bytes()
    g = scene.decode()
    # kept: means in float32, scales, quats and sh in float16 (features are recomputed)
    per_gaussian = 3 * 4 + (3 + 4 + g.sh[0].numel()) * 2
    assert len(g) * per_gaussian <= scene.memory_bytes() - before < len(g) * (per_gaussian + g.features.shape[1] * 4)


@pytest.mark.realdata
def test_decodes_racing_folds_and_each_other_each_decode_their_own_inputs(shelf):
    # as the service runs them: folds and the copy of the inputs under one lock, decodes outside it
    scene, lock = Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.008)), threading.Lock()
    scene.fold(shelf[0])
    decoded, errors, started, folded = [], [], threading.Barrier(3, timeout=120), threading.Event()

    def view() -> None:
        with lock:
            inputs = scene.decode_inputs()
        decoded.append((inputs, scene.decode_from(inputs)))

    def viewer() -> None:
        try:
            view()  # one decode before any fold, then decodes until the folds are done, then one more
            started.wait()
            while not folded.is_set():
                view()
            view()
        except Exception as error:  # noqa: BLE001 -- reported by the main thread
            errors.append(error)
            started.abort()  # the main thread must not wait for a viewer that is gone

    viewers = [threading.Thread(target=viewer) for _ in range(2)]
    for t in viewers:
        t.start()
    try:
        started.wait()
    except threading.BrokenBarrierError:
        pytest.fail(f"a viewer failed before the folds: {errors}")
    for frame in shelf[1:5]:
        with lock:
            scene.fold(frame)
    folded.set()
    for t in viewers:
        t.join()
    assert not errors and len(decoded) >= 4
    assert len({len(g) for _, g in decoded}) > 1  # the viewers saw the scene grow
    for inputs, g in decoded:
        assert_same_gaussians(g, from_scratch(scene, inputs))


def test_gaussians_are_decoded_once_per_change_and_per_level_of_detail(shelf):
    scene = folded_scene(shelf[:3])
    counts = decoded_row_counts(scene)
    g = scene.gaussians()
    assert scene.gaussians() is g and scene.gaussians(len(scene)) is g  # a limit that leaves out nothing is the full decode
    assert len(counts) == 1
    fewer = scene.gaussians(len(g) // 2)
    assert len(fewer) == len(g) // 2 and scene.gaussians(len(g) // 2) is fewer
    assert_same_gaussians(fewer, scene.decode(len(g) // 2))
    with pytest.raises(ValueError, match="max_gaussians"):
        scene.gaussians(-1)
    scene.fold(shelf[3])
    after = scene.gaussians()
    assert after is not g and len(after) != len(g)
    assert_same_gaussians(after, from_scratch(scene))


def without_features(g):
    return dataclasses.replace(g, features=None)


def test_gaussians_without_features_leave_out_only_f_scene_and_read_none_of_it_for_reused_rows(shelf, monkeypatch):
    scene = folded_scene(shelf[:3])
    plain = scene.gaussians(features=False)  # from scratch: every row decoded afresh
    assert plain.features is None
    assert_same_gaussians(plain, without_features(from_scratch(scene)))
    assert scene.gaussians(features=False) is plain  # kept for this state
    full = scene.gaussians()  # F_scene wanted: a decode again, which reuses every decoded row
    assert full.features is not None
    assert_same_gaussians(full, from_scratch(scene))
    assert scene.gaussians(features=False) is full  # Gaussians with F_scene serve a caller that does not need it

    read = []
    monkeypatch.setattr("canonical_core.scene.decoding.scene_features", lambda *a: read.append(1) or scene_features(*a))
    for frame in shelf[3:5]:  # after a fold: the reused rows' F_scene is read only when wanted
        scene.fold(frame)
        after = scene.gaussians(features=False)
        assert after.features is None and not read
        assert_same_gaussians(after, without_features(from_scratch(scene)))
        assert_same_gaussians(scene.gaussians(), from_scratch(scene))
        assert len(read) == 1
        read.clear()
    fewer = scene.gaussians(len(scene) // 3, features=False)  # a level of detail too
    assert fewer.features is None
    assert_same_gaussians(fewer, without_features(scene.decode(len(scene) // 3)))
    scene.fold(shelf[5])  # the library's decodes take the same option
    inputs = scene.decode_inputs()
    assert_same_gaussians(scene.decode_from(inputs, features=False), without_features(from_scratch(scene, inputs)))
    assert_same_gaussians(scene.decode(features=False), without_features(scene.decode()))


def test_the_decode_cache_stays_bounded_across_decoder_changes_and_levels_of_detail(shelf):
    scene = folded_scene(shelf[:3])
    for _ in range(3):  # a changed decoder (a loaded model, a training step): its earlier Gaussians never serve again
        with torch.no_grad():
            scene.decoder.opacity.a.add_(0.0)  # a new parameter version, the same values
        plain, full = scene.gaussians(features=False), scene.gaussians()
        assert plain.features is None and full.features is not None
        assert scene.gaussians(features=False) is full and scene.gaussians() is full
    for k in range(2, 8):  # more levels of detail than the cache holds
        assert len(scene.gaussians(len(scene) // k)) == len(scene) // k
    assert len(scene._decoding._gaussians) <= DECODE_CACHE_ENTRIES
    assert scene.gaussians() is full  # the full decode outlasts the levels of detail
    assert_same_gaussians(full, from_scratch(scene))


def test_concurrent_requests_of_an_unchanged_scene_decode_once(shelf):
    scene = folded_scene(shelf[:3])
    decodes, decode = [], scene._decoding.finish

    def counting(*args, **kwargs):
        decodes.append(1)
        return decode(*args, **kwargs)

    scene._decoding.finish = counting
    start, answers = threading.Barrier(4), []

    def request():
        start.wait()
        answers.append(scene.gaussians())

    threads = [threading.Thread(target=request) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(decodes) == 1 and len(answers) == 4 and all(a is answers[0] for a in answers)


@pytest.mark.parametrize("free_space", [True, False])
@pytest.mark.parametrize("min_support", [0.0, 0.3])
@pytest.mark.parametrize("n", [10_001, 5])  # more rows than the scan's blocks, and fewer
def test_decoded_rows_equals_its_reference(free_space, min_support, n):
    """The one-pass row selection, the rows' support and free space, and the support unit against the
    PyTorch rule (`support_unit`, masks)."""
    rng = np.random.default_rng(3)
    sums = {"r_sum": rng.gamma(1.0, 0.5, n).astype(np.float32), "n_obs": rng.integers(0, 6, n).astype(np.int32),
            "free": rng.gamma(1.0, 0.4, n).astype(np.float32)}
    sums["r_sum"][sums["n_obs"] == 0] = 0.0
    config = SceneConfig(colour_solve=UNSOLVED, voxel_size=0.01, free_space={"enabled": free_space})
    keep, support, free, unit = decoded_rows(sums, min_support, config)
    r, f = torch.from_numpy(sums["r_sum"]), torch.from_numpy(sums["free"])
    mask = r > min_support
    if free_space:
        mask &= f <= config.free_space.dominance * r
    np.testing.assert_array_equal(keep, torch.nonzero(mask).squeeze(1).numpy())
    assert torch.equal(support, r[mask]) and torch.equal(free, f[mask])
    assert unit == support_unit(r, torch.from_numpy(sums["n_obs"]))
    none_seen = {k: v[:0] for k, v in sums.items()}
    assert decoded_rows(none_seen, 0.0, config).unit == support_unit(r[:0], torch.from_numpy(sums["n_obs"][:0]))


def test_scene_features_equal_the_fields_features():
    scene = folded_scene([make_frame(np.full((12, 16), 2.0, np.float32))], 0.05)
    sums = scene.sums()
    rows = np.array([3, 0, len(scene) - 1, 3], np.int64)
    expected = fields_from_sums({k: v[rows] for k, v in sums.items()}, scene.config, sort=False)["features"]
    assert torch.equal(scene_features(sums, rows, scene.config.research.eps), expected)


def test_gather_rows_equals_fancy_indexing_on_the_scenes_columns():
    scene = folded_scene([make_frame(np.full((12, 16), 2.0, np.float32))], 0.05)
    sums = scene.decode_inputs().sums  # strided views of the rows, 1-D arrays, uint8 colours, [V, 0] labels
    assert not sums["f_mean"].flags.c_contiguous and not sums["r_sum"].flags.c_contiguous
    rows = np.array([5, 0, len(scene) - 1, 5], np.int64)
    for name, column in sums.items():
        gathered = gather_rows(column, rows)
        assert gathered.shape == column[rows].shape and gathered.numpy().dtype == column.dtype, name
        np.testing.assert_array_equal(gathered.numpy(), column[rows], err_msg=name)
    assert gather_rows(sums["f_mean"], np.empty(0, np.int64)).shape == (0, sums["f_mean"].shape[1])


def test_gather_rows_widens_float16_to_the_same_float32_as_numpy():
    # every float16 bit pattern but NaN's payloads: normals, subnormals, both zeros, both infinities
    bits = np.arange(0, 1 << 16, dtype=np.uint32).astype(np.uint16)
    halves = bits.view(np.float16)
    halves = halves[~np.isnan(halves)].reshape(-1, 5)[:, ::-1]  # [V, 5] (63490 of them), a strided view
    rows = np.r_[np.random.default_rng(0).permutation(len(halves)), 7]  # every row, one twice
    widened = gather_rows(halves, rows, widen=True)
    assert widened.dtype == torch.float32 and widened.shape == (len(halves) + 1, 5)
    np.testing.assert_array_equal(widened.numpy().view(np.uint32), halves[rows].astype(np.float32).view(np.uint32))
    assert gather_rows(halves, rows).dtype == torch.float16  # without widen: as stored
    nan = np.full((2, 3), np.nan, np.float16)
    assert torch.isnan(gather_rows(nan, np.array([1, 0]), widen=True)).all()
    assert gather_rows(halves, np.empty(0, np.int64), widen=True).shape == (0, 5)
    floats = np.arange(12, dtype=np.float32).reshape(4, 3)  # other dtypes: copied as they are
    assert torch.equal(gather_rows(floats, np.array([2]), widen=True), torch.from_numpy(floats[[2]]))


def test_an_empty_scene_decodes_to_no_gaussians():
    scene = Scene(SceneConfig(colour_solve=UNSOLVED, voxel_size=0.05))
    assert len(scene.decode()) == 0 and len(scene.decode_from(scene.decode_inputs())) == 0
    empty = scene.decode_inputs().sums
    for name, column in empty.items():
        assert gather_rows(column, np.empty(0, np.int64)).shape == column.shape, name


def test_decoded_rows_give_back_each_rows_latest_parts_whether_stored_new_or_over_old_ones():
    # all new (one run of slots), then old and new rows mixed (an indexed copy), then new rows again
    # after the parts grew (a run that starts past the first slots): every row reads back what was
    # stored for it last, float16 parts rounded so
    g = torch.Generator().manual_seed(3)
    kept, latest = DecodedRows(("key",)), {}
    for rows in (np.array([4, 9, 2, 7]), np.array([9, 11, 4, 0]), np.arange(20, 31)):
        parts = {"means": torch.randn(len(rows), 3, generator=g), "scales": torch.rand(len(rows), 3, generator=g),
                 "quats": torch.randn(len(rows), 4, generator=g), "sh": torch.randn(len(rows), 4, 3, generator=g),
                 "labels": None}
        kept.store(rows, np.full(len(rows), len(latest), np.int32), parts)
        for i, row in enumerate(rows):
            latest[int(row)] = {k: v[i] for k, v in parts.items() if v is not None}
    rows = np.array(sorted(latest))
    back = kept.gather(rows)
    assert back["labels"] is None
    for name in ("means", "scales", "quats", "sh"):
        expected = torch.stack([latest[int(r)][name] for r in rows])
        expected = expected.half().float() if name in HALF_PARTS else expected
        assert back[name].dtype == torch.float32 and torch.equal(back[name], expected), name
