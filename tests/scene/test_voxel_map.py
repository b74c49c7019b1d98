"""The voxel map's hash table and growth: every key finds its own row through any growth (rows
grown in place, the table replaced by a successor filled a slice per fold), lookups end even in a
full table, the cap is enforced before anything changes, and the lattice's extreme keys are stored
and found like any other."""

import numpy as np
import pytest

from canonical_core import Scene, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.config import KEY_BITS, KEY_OFFSET
from canonical_core.scene.free_space import CHUNK
from canonical_core.scene.hashing import insert_range_kernel, lookup_kernel, remove_range_kernel, voxel_keys_kernel
from canonical_core.scene.voxel_map import (ARRAYS, MAX_TABLE_LOAD, NEXT_TABLE_LOAD, CapacityError, VoxelMap,
                                            table_size)

FEATURE_DIM = 4


def random_sums(voxels: VoxelMap, keys: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """Sums as `VoxelMap.sums` returns them, for ``keys``, with random values in every field."""
    rng = np.random.default_rng(seed)
    n = len(keys)
    sums = {name: rng.integers(0, 100, (n, *shape)).astype(dtype) for name, (dtype, shape) in ARRAYS.items()}
    sums["keys"] = np.asarray(keys, np.int64)
    dtypes = {name: array.dtype for name, array in voxels.sums().items()}  # float32, float16, int8 (the direction)
    sums |= {name: (rng.integers(-127, 128, (n, *shape)) if dtypes[name].kind == "i" else rng.standard_normal((n, *shape)))
             .astype(dtypes[name]) for name, (_, _, shape) in voxels.stored.columns.items()}
    return sums


def distinct_keys(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.choice(np.int64(1) << np.int64(3 * KEY_BITS - 2), size=n, replace=False).astype(np.int64)


def load(keys: np.ndarray, initial_capacity: int = 16) -> tuple[VoxelMap, dict[str, np.ndarray]]:
    voxels = VoxelMap(FEATURE_DIM, sh_degree=1, initial_capacity=initial_capacity)
    sums = random_sums(voxels, keys)
    voxels.load_sums(sums)
    return voxels, sums


def assert_sums_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_growth_keeps_every_key_and_row():
    voxels, sums = load(distinct_keys(12))
    table_before = voxels.table.shape[0]
    voxels.reserve(5000)  # rows x1.5 or more, and a table rebuilt at a new size
    assert voxels.capacity >= 5000 and voxels.table.shape[0] > table_before
    assert len(voxels) == 12
    np.testing.assert_array_equal(voxels.find(sums["keys"]), np.arange(12))
    assert_sums_equal(voxels.sums(), {k: v for k, v in sums.items()} | {"label_sum": np.zeros((12, 0), np.float32)})


def append(voxels: VoxelMap, keys: np.ndarray) -> None:
    """What a fold does with new voxels: room, keys written and entered into the table, commit."""
    n = len(voxels)
    voxels.reserve(n + len(keys))
    voxels.state["keys"][n: n + len(keys)] = keys
    insert_range_kernel(voxels.table, voxels.state["keys"], n, n + len(keys))
    voxels.commit(np.empty(0, np.int64), len(keys))


def test_rows_grow_in_place_without_copying():
    voxels, sums = load(distinct_keys(100))
    rows = voxels.state["rows"]
    voxels.reserve(20 * voxels.capacity)
    assert np.shares_memory(rows, voxels.state["rows"])  # the same block, a longer view
    assert_sums_equal(voxels.sums(), sums | {"label_sum": np.zeros((100, 0), np.float32)})


def test_the_successor_table_fills_a_slice_per_fold_and_every_key_is_found_throughout():
    voxels = VoxelMap(FEATURE_DIM, sh_degree=0, initial_capacity=1 << 12)
    keys = distinct_keys(60_000)
    sizes, filling = set(), 0
    for start in range(0, len(keys), 500):  # folds of 500 new voxels
        append(voxels, keys[start: start + 500])
        n = len(voxels)
        sizes.add(voxels.table.shape[0])
        filling += voxels._next_table is not None
        assert n <= MAX_TABLE_LOAD * voxels.table.shape[0]
        probe = np.r_[keys[:n: 97], keys[n - 1]]
        np.testing.assert_array_equal(voxels.find(probe), np.r_[np.arange(0, n, 97), n - 1])
    assert len(sizes) >= 4 and filling > 0  # it grew several times, through successors part-filled over folds
    np.testing.assert_array_equal(voxels.find(keys), np.arange(len(keys)))


def test_a_fold_that_outruns_the_successor_finishes_it_at_once():
    voxels = VoxelMap(FEATURE_DIM, sh_degree=0, initial_capacity=1 << 12)
    keys = distinct_keys(200_000)
    append(voxels, keys[:100_000])  # one rehash, to a table at a load below NEXT_TABLE_LOAD
    slots = voxels.table.shape[0]
    assert voxels._next_table is None and 100_000 <= NEXT_TABLE_LOAD * slots
    append(voxels, keys[100_000:140_000])  # past NEXT_TABLE_LOAD: the successor gets its first slice
    assert voxels._next_table is not None and voxels._next_filled < len(voxels)
    append(voxels, keys[140_000:])  # past MAX_TABLE_LOAD of the table in place: the successor completes
    assert voxels.table.shape[0] == 2 * slots and voxels._next_table is None
    np.testing.assert_array_equal(voxels.find(keys), np.arange(len(keys)))


def test_the_table_load_stays_below_the_limit_at_every_size():
    voxels = VoxelMap(FEATURE_DIM, sh_degree=0, initial_capacity=16)
    for n in (1, 11, 12, 100, 1000, 12345):
        voxels.reserve(n)
        assert n <= MAX_TABLE_LOAD * voxels.table.shape[0] and voxels.capacity >= n
        assert table_size(n) & (table_size(n) - 1) == 0  # a power of two: slots are masked, not divided


def test_folding_into_a_tiny_map_equals_folding_into_a_large_one():
    """The real fold through many growths of rows and table: same state, and every stored key finds its row."""
    frames = synthetic_rgbd(num_frames=3, width=64, height=48)
    grown, roomy = Scene(SceneConfig(voxel_size=0.02), initial_capacity=16), Scene(SceneConfig(voxel_size=0.02))
    for frame in frames:
        grown.fold(frame)
        roomy.fold(frame)
    assert grown.capacity < roomy.capacity and grown.digest() == roomy.digest()
    keys = grown.sums()["keys"]
    np.testing.assert_array_equal(grown._voxels.find(keys), np.arange(len(keys)))


def test_lookups_of_absent_keys_end_in_a_full_table():
    voxels, sums = load(distinct_keys(16), initial_capacity=16)
    voxels.table = np.empty(16, np.int32)  # a table with no empty slot left (the map never makes one)
    voxels.rebuild_table()
    assert (voxels.table >= 0).all()
    absent = np.setdiff1d(distinct_keys(40, seed=7), sums["keys"])[:8]
    np.testing.assert_array_equal(voxels.find(absent), -1)
    np.testing.assert_array_equal(np.sort(voxels.find(sums["keys"])), np.arange(16))


def home_slot(keys: np.ndarray, table_slots: int) -> np.ndarray:
    """The slot a key's probe starts at: the multiplicative hash `hashing.home_slot` computes."""
    h = keys.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    return ((h >> np.uint64(29)) & np.uint64(table_slots - 1)).astype(np.int64)


def test_keys_that_share_a_home_slot_probe_to_the_next_free_ones():
    candidates = distinct_keys(2000)
    slots = table_size(16)
    home = home_slot(candidates, slots)
    target = np.bincount(home).argmax()
    keys = candidates[home == target][:3]  # three keys whose probes all start at one slot
    assert len(keys) == 3
    voxels, _ = load(keys)
    assert voxels.table.shape[0] == slots
    np.testing.assert_array_equal(voxels.find(keys), [0, 1, 2])
    np.testing.assert_array_equal(voxels.table[(target + np.arange(3)) % slots], [0, 1, 2])  # linear probing, in order


@pytest.mark.parametrize("seed", range(6))
def test_removing_the_last_entered_leaves_the_table_as_the_first_alone_would(seed):
    """Crowded tables (load 0.75: long clusters, some wrapping past the last slot), every cut."""
    keys = distinct_keys(12, seed=seed)
    for n in range(len(keys) + 1):
        table = np.full(16, -1, np.int32)
        insert_range_kernel(table, keys, 0, len(keys))
        remove_range_kernel(table, keys, n, len(keys))
        alone = np.full(16, -1, np.int32)
        insert_range_kernel(alone, keys, 0, n)
        np.testing.assert_array_equal(table, alone, err_msg=f"n={n}")
        found = np.empty(len(keys), np.int32)
        lookup_kernel(table, keys, keys, found)
        np.testing.assert_array_equal(found, np.where(np.arange(len(keys)) < n, np.arange(len(keys)), -1))


@pytest.mark.parametrize("seed", range(6))
def test_removing_voxels_entered_before_others_keeps_every_other_voxel_found(seed):
    """Not the last entered (the roll-back never does this): the backward shift moves later entries
    into the holes, so every chain stays whole."""
    keys = distinct_keys(12, seed=seed)
    table = np.full(16, -1, np.int32)
    insert_range_kernel(table, keys, 0, len(keys))
    remove_range_kernel(table, keys, 2, 7)
    found = np.empty(len(keys), np.int32)
    lookup_kernel(table, keys, keys, found)
    kept = np.r_[0:2, 7:12]
    np.testing.assert_array_equal(found, np.where(np.isin(np.arange(len(keys)), kept), np.arange(len(keys)), -1))
    np.testing.assert_array_equal(np.sort(table[table >= 0]), kept)


def test_truncate_drops_the_last_voxels_as_if_never_entered():
    keys = distinct_keys(3 * CHUNK + 100)
    voxels, sums = load(keys)
    n = CHUNK + 300  # inside the second chunk
    voxels.truncate(n)
    fresh, _ = load(keys[:n])
    fresh.load_sums({name: value[:n] for name, value in sums.items()})
    assert len(voxels) == n
    assert_sums_equal(voxels.sums(), fresh.sums())
    rebuilt = voxels.table.copy()
    voxels.rebuild_table()
    np.testing.assert_array_equal(rebuilt, voxels.table)
    chunks = -(-n // CHUNK)
    np.testing.assert_array_equal(voxels.chunk_lo[:chunks], fresh.chunk_lo[:chunks])
    np.testing.assert_array_equal(voxels.chunk_hi[:chunks], fresh.chunk_hi[:chunks])
    assert not voxels.chunk_lo[chunks:].any() and not voxels.chunk_hi[chunks:].any()
    assert not voxels.state["rows"][n: len(keys)].any() and not voxels.state["keys"][n: len(keys)].any()
    np.testing.assert_array_equal(voxels.find(keys[n:]), -1)
    with pytest.raises(ValueError, match=r"^n: expected a voxel count in \[0, 1324\]"):
        voxels.truncate(n + 1)


def test_the_cap_is_checked_before_anything_changes():
    voxels = VoxelMap(FEATURE_DIM, sh_degree=0, initial_capacity=16, max_voxels=5)
    voxels.check_room(5)
    with pytest.raises(CapacityError, match="max_voxels: .* 6 voxels, above the cap of 5"):
        voxels.check_room(6)
    assert issubclass(CapacityError, ValueError) and len(voxels) == 0


def test_a_scene_at_its_cap_refuses_the_frame_unchanged():
    frames = synthetic_rgbd(num_frames=2, width=64, height=48)
    scene = Scene(SceneConfig(voxel_size=0.02, max_voxels=2500))
    scene.fold(frames[0])
    before = scene.digest()
    with pytest.raises(CapacityError, match="max_voxels"):
        scene.fold(frames[1])
    assert scene.digest() == before


def test_keys_at_the_lattice_extremes_are_stored_and_found():
    low, high = -KEY_OFFSET, KEY_OFFSET - 1  # the first and last voxel index on each axis
    points = np.array([[low, low, low], [high + 0.5, high + 0.5, high + 0.5], [low, high + 0.5, 0.5],
                       [high + 1.0, 0, 0], [low - 1.0, 0, 0]], np.float32)
    keys = np.empty(len(points), np.int64)
    voxel_keys_kernel(points, np.float32(1.0), keys)
    top = (1 << KEY_BITS) - 1
    assert keys[0] == 0 and keys[1] == (top << 2 * KEY_BITS) | (top << KEY_BITS) | top == np.iinfo(np.int64).max
    assert keys[2] == (top << KEY_BITS) | KEY_OFFSET
    assert keys[3] == -1 and keys[4] == -1  # one past either end: outside the lattice
    voxels, _ = load(keys[:3])
    np.testing.assert_array_equal(voxels.find(keys[:3]), [0, 1, 2])
    np.testing.assert_array_equal(voxels.find(np.array([1, top], np.int64)), [-1, -1])


def test_a_reservation_the_system_refuses_falls_back_to_smaller_blocks(monkeypatch):
    # far beyond any machine's address space: every block is refused until it is a quarter of a
    # quarter ... of that, and the map still works (and grows by copying past its smaller blocks)
    monkeypatch.setattr("canonical_core.scene.voxel_map.RESERVED_ROWS", 1 << 46)
    voxels, sums = load(distinct_keys(3000))
    rows = voxels._backing["rows"].shape[0]
    assert 3000 <= rows < 1 << 46
    np.testing.assert_array_equal(voxels.find(sums["keys"]), np.arange(3000))


def test_a_preallocated_scene_folds_the_same_and_never_grows_below_its_reservation(shelf_frames):
    frames = shelf_frames[:6]
    config = SceneConfig(voxel_size=0.004, colour_solve={"views": 0})  # no kept views: the map's memory alone
    plain, reserved = Scene(config), Scene(config)
    reserved.preallocate(200_000)
    voxels = reserved._voxels
    table, rows = voxels.table, voxels.state["rows"]
    assert reserved.memory_bytes() >= 200_000 * rows.strides[0] and len(reserved) == 0
    plain.fold(frames[0])
    reserved.fold(frames[0])
    with_one = reserved.memory_bytes()
    for frame in frames[1:]:
        plain.fold(frame)
        reserved.fold(frame)
    assert 0 < len(reserved) <= 200_000 and reserved.digest() == plain.digest()
    # no growth: the same rows' view, the same table, no successor started, no new memory counted
    assert voxels.table is table and voxels.state["rows"] is rows and voxels._next_table is None
    assert reserved.memory_bytes() == with_one


def test_preallocating_a_scene_that_holds_voxels_keeps_them():
    frames = synthetic_rgbd(num_frames=4, width=64, height=48)
    config = SceneConfig(voxel_size=0.02)
    plain, reserved = Scene(config, initial_capacity=16), Scene(config, initial_capacity=16)
    for frame in frames[:2]:
        plain.fold(frame)
        reserved.fold(frame)
    reserved.preallocate(50_000)
    assert reserved.digest() == plain.digest() and reserved.capacity >= 50_000
    keys = reserved.sums()["keys"]
    np.testing.assert_array_equal(reserved._voxels.find(keys), np.arange(len(keys)))
    for frame in frames[2:]:
        plain.fold(frame)
        reserved.fold(frame)
    assert reserved.digest() == plain.digest()


@pytest.mark.parametrize("bad, message", [(-1, "non-negative integer"), (2.5, "non-negative integer"),
                                          (True, "non-negative integer"), ("7", "non-negative integer"),
                                          (101, "above max_voxels")])
def test_a_bad_preallocation_is_refused_and_changes_nothing(bad, message):
    scene = Scene(SceneConfig(voxel_size=0.02, max_voxels=100), initial_capacity=16)
    capacity, memory = scene.capacity, scene.memory_bytes()
    with pytest.raises(ValueError, match=f"voxels: .*{message}"):
        scene.preallocate(bad)
    assert scene.capacity == capacity and scene.memory_bytes() == memory
