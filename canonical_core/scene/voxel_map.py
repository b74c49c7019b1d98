"""The voxel map: per-voxel records in insertion order behind an open-addressing hash of voxel keys.

It knows nothing of frames. It holds, for ``len(map)`` voxels:

- ``keys`` [V] int64, the packed lattice coordinates (`hashing` packs (i, j, k) into 21 bits each);
- ``rows`` [V, width] float32 and ``half`` [V, half_width] float16 bits, the representative and
  every weighted sum (`kernels.VoxelRows`), stored as `stored.StoredRows` lays them out;
- ``rep_rgb`` [V, 3] uint8, ``free`` [V] float32 (see-through evidence), ``n_obs`` [V] int32;
- ``table``, a power-of-two hash table of voxel indices (-1 empty, linear probing), kept at a load
  of at most `MAX_TABLE_LOAD` so that a probe ends after a few slots. Its successor, twice the
  size, is filled a slice per fold from a load of `NEXT_TABLE_LOAD` on and replaces it once it
  holds every voxel, so no fold pays for rehashing the whole map;
- per chunk of `free_space.CHUNK` voxels, their keys' bounding box (the free-space kernels skip
  chunks outside a frustum);
- per voxel, the stamp of the last change of its sums (`changed_at`, int32), which the decoder side
  uses to decode again only what changed. Stamps are unique in the process within a stamp epoch
  (`stamps.StampClock`); a map restamps all its voxels when it first stamps in a new epoch, so equal
  stamps of one epoch mean equal sums.

Growth never copies the records on the fold path: each per-voxel array is a view of the first
`capacity` rows of a zeroed block of `RESERVED_ROWS` rows allocated up front. A block that large is
address space, not memory: the allocator maps it lazily, and a page costs memory (and a zero fill)
only when a fold first writes a row in it. Growing the capacity is a new, longer view. Only a map
that outgrows its block (or one where the reservation is refused) copies its rows into a new one.

Integration (`integrate`) writes the records; the snapshot reads and restores them as arrays of
the stored fields (`sums`, `load_sums`).
"""

from __future__ import annotations

import math
import mmap

import numpy as np
import torch

from ..config import MAX_VOXELS
from . import stamps
from .fields import sh_sum_widths, unpack_keys
from .free_space import CHUNK, update_chunk_boxes_kernel
from .hashing import insert_range_kernel, lookup_kernel, remove_range_kernel
from .kernels import VoxelRows
from .stored import StoredRows
from .sums import copy_bytes, sums_view

MAX_TABLE_LOAD = 0.7  # the table's largest load: linear probing stays short below it
# rows reserved per array up front (about 5 GB of address space with the default layout, none of
# it memory until written): a map copies its records only if it outgrows this
RESERVED_ROWS = 1 << 24
NEXT_TABLE_LOAD = 0.5  # the load at which the next table starts filling
# hash slots a voxel can take at most: 1 / (MAX_TABLE_LOAD / 2) in the table, twice that in its successor
TABLE_SLOTS_PER_NEW_VOXEL = 9
NEXT_TABLE_CLEAR = 1 / 8  # slots of it marked empty per fold (its pages are first touched then)
NEXT_TABLE_SLICE = 1 / 32  # voxels entered into it per fold once it is clear, as a share of its slots

# per-voxel arrays beside the stored record (`rows` and `half`, `stored`): name -> (dtype, trailing shape)
ARRAYS = {
    "keys": (np.int64, ()),
    "rep_rgb": (np.uint8, (3,)),  # input colours are 8-bit: lossless
    "free": (np.float32, ()),  # written by the free-space kernels, which scan it with the keys
    "n_obs": (np.int32, ()),
}


class CapacityError(ValueError):
    """A fold would take the scene past ``SceneConfig.max_voxels``; the scene is unchanged."""


def next_pow2(n: int) -> int:
    """The smallest power of two >= ``n`` (and >= 16)."""
    return 1 << max(4, int(n - 1).bit_length())


def lazy_zeros(shape: tuple[int, ...], dtype) -> np.ndarray:
    """A zeroed array whose pages become memory only as they are written: an anonymous mapping of its
    own. ``np.zeros`` gives that only while malloc maps the block afresh; glibc raises its threshold
    for that (up to 32 MiB) as a process frees large blocks, and then zeroes a block from its heap by
    writing every page, so that a map's reserved rows would all be memory from the start (a service
    making and deleting sessions held a session's whole reserve for each). No huge pages: a small
    map would take one for each of its arrays, and a large one folds no faster with them
    (`docs/experiments.md`). MemoryError where the system refuses the address space."""
    count = math.prod(shape)
    nbytes = max(count * np.dtype(dtype).itemsize, 1)
    try:
        block = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    except OSError as exc:  # an overcommit limit, ``ulimit -v``
        raise MemoryError(f"{nbytes} bytes of address space: {exc.strerror or exc}") from None
    return np.frombuffer(block, dtype, count=count).reshape(shape)


def table_size(n_voxels: int) -> int:
    """Hash-table slots for ``n_voxels`` at a load of at most `MAX_TABLE_LOAD`."""
    return next_pow2(int(n_voxels / MAX_TABLE_LOAD) + 1)


class VoxelMap:
    """Sparse voxel records with hash lookup, grown on demand up to an optional cap.

    Args:
        feature_dim: L, the feature channels of each record.
        sh_degree: the SH degree whose fit sums each record keeps.
        initial_capacity: rows counted as allocated at the start (growth is x1.5); the backing
            block reserves `RESERVED_ROWS` (at most ``max_voxels``, at least this).
        max_voxels: the cap `check_room` enforces (None: no cap).

    Example:
        >>> voxels = VoxelMap(feature_dim=4, sh_degree=0, initial_capacity=16)
        >>> len(voxels), voxels.capacity, voxels.table.shape[0]
        (0, 16, 32)
    """

    def __init__(self, feature_dim: int, sh_degree: int, initial_capacity: int = 1 << 15,
                 max_voxels: int | None = None):
        if isinstance(initial_capacity, bool) or not isinstance(initial_capacity, (int, np.integer)) \
                or not 0 <= initial_capacity <= MAX_VOXELS:
            raise ValueError(f"initial_capacity: expected a whole number of voxels in [0, {MAX_VOXELS}], "
                             f"got {initial_capacity!r}")
        self.feature_dim, self.sh_degree, self.max_voxels = feature_dim, sh_degree, max_voxels
        self.layout = VoxelRows(feature_dim, sh_sum_widths(sh_degree))
        self.stored = StoredRows(self.layout)
        self.n = 0
        self._written = 0  # rows of the blocks ever written: the part of them that is memory
        self._backing: dict[str, np.ndarray] = {}  # the reserved blocks that `state` and `changed_at` view
        self._provide(initial_capacity)
        self.table = np.full(table_size(initial_capacity), -1, np.int32)
        self._next_table: np.ndarray | None = None  # the successor: slots [0, _next_cleared) marked empty,
        self._next_cleared = self._next_filled = 0  # then voxels [0, _next_filled) entered
        self.chunk_lo = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
        self.chunk_hi = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
        # an `undo.FoldUndo` while a fold keeps one: the integration enters what it is about to overwrite
        self.journal = None
        self.stamp_epoch = 0  # the `stamps.StampClock` epoch of every stamp in `changed_at`

    def __len__(self) -> int:
        return self.n

    @property
    def capacity(self) -> int:
        return int(self.state["keys"].shape[0])

    @property
    def label_dim(self) -> int:
        return self.layout.label_dim

    def _shapes(self) -> dict[str, tuple[type, tuple[int, ...]]]:
        return ARRAYS | {"rows": (np.float32, (self.stored.width,)), "half": (np.uint16, (self.stored.half_width,)),
                         "changed_at": (np.int32, ())}

    def _reserve(self, capacity: int, rows: int, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
        """Zeroed blocks of ``rows`` rows (of every array, or of ``names``), fewer (down to
        ``capacity``) where the system refuses that much address space (a small machine's
        overcommit limit, ``ulimit -v``)."""
        shapes = {k: v for k, v in self._shapes().items() if names is None or k in names}
        while True:
            try:
                return {name: lazy_zeros((rows, *shape), dtype) for name, (dtype, shape) in shapes.items()}
            except MemoryError:
                if rows == capacity:
                    raise
                rows = max(capacity, rows // 4)

    def _provide(self, capacity: int) -> None:
        """Point `state` and `changed_at` at ``capacity`` rows holding the current `len(self)` ones:
        a longer view of the backing blocks where they are large enough, else new blocks (sized for
        ``capacity`` at least) that the current rows are copied into."""
        backing = self._backing
        if not backing or capacity > min(block.shape[0] for block in backing.values()):
            backing = self._reserve(capacity, max(capacity, min(RESERVED_ROWS, self.max_voxels or RESERVED_ROWS)))
            for name, block in self._backing.items():
                backing[name][: self.n] = block[: self.n]
            self._backing, self._written = backing, self.n
        self.state = {name: block[:capacity] for name, block in backing.items() if name != "changed_at"}
        self.changed_at = backing["changed_at"][:capacity]

    # -- growth -------------------------------------------------------------------------------
    def check_room(self, n_new: int) -> None:
        """Raise `CapacityError` if ``n_new`` more voxels would exceed ``max_voxels``."""
        cap = self.max_voxels
        if cap is not None and self.n + n_new > cap:
            raise CapacityError(
                f"max_voxels: folding this frame would grow the scene to {self.n + n_new} voxels, above the cap of {cap}"
            )

    def reserve(self, n_voxels: int) -> None:
        """Grow the rows (x1.5, amortised; a view of the reserved blocks, no copy) and the hash table
        (load <= MAX_TABLE_LOAD) to hold ``n_voxels``."""
        if n_voxels > self.capacity:
            self._provide(max(n_voxels, int(self.capacity * 1.5)))
            for name in ("chunk_lo", "chunk_hi"):
                grown = np.zeros((self.capacity // CHUNK + 1, 3), np.int64)
                grown[: getattr(self, name).shape[0]] = getattr(self, name)
                setattr(self, name, grown)
        if n_voxels > MAX_TABLE_LOAD * self.table.shape[0]:  # a fold outran the successor: finish it now
            successor = self._next_table
            if successor is not None and n_voxels <= MAX_TABLE_LOAD * successor.shape[0]:
                successor[self._next_cleared:] = -1
                insert_range_kernel(successor, self.state["keys"], self._next_filled, self.n)
                self.table = successor
            else:
                self.table = np.empty(table_size(n_voxels), np.int32)
                self.rebuild_table()
            self._next_table = None

    def preallocate(self, n_voxels: int) -> None:
        """Commit the memory of ``n_voxels`` voxels now: their rows written (zeros) and the hash table
        sized so that it neither grows nor starts its successor below that many. A map grows into
        fresh memory, and the system faults each new page in and zeroes it on the fold that first
        writes it (on a virtual machine, the first touch of a page costs several times more); folds
        up to ``n_voxels`` no longer wait for that. What `nbytes` counts includes the committed rows."""
        if isinstance(n_voxels, bool) or not isinstance(n_voxels, (int, np.integer)) or n_voxels < 0:
            raise ValueError(f"voxels: expected a non-negative integer, got {n_voxels!r}")
        if self.max_voxels is not None and n_voxels > self.max_voxels:
            raise ValueError(f"voxels: {n_voxels} is above max_voxels ({self.max_voxels})")
        if n_voxels > MAX_VOXELS:
            raise ValueError(f"voxels: {n_voxels} is above the most a scene holds ({MAX_VOXELS})")
        n_voxels = int(n_voxels)
        try:
            if n_voxels > self._written:
                self.reserve(n_voxels)
                for array in (*self.state.values(), self.changed_at):
                    array[self.n: n_voxels] = 0  # rows past len(self) are zero: written, their pages are committed
                self._written = n_voxels
            size = next_pow2(int(n_voxels / NEXT_TABLE_LOAD) + 1)
            if size > self.table.shape[0]:
                self.table = np.empty(size, np.int32)
                self.rebuild_table()
        except MemoryError:  # a refused allocation replaces nothing: the voxels and their table are as they were
            asked = n_voxels * self.new_voxel_bytes() / 2**30
            raise ValueError(f"voxels: {n_voxels} voxels ask for about {asked:.3g} GiB, more memory than the "
                             "system grants") from None

    def _fill_next_table(self) -> None:
        """One fold's share of the successor table (started at `NEXT_TABLE_LOAD`): a slice of it
        marked empty, or once all of it is, the next slice of voxels entered; it replaces the table
        in place once it holds them all."""
        if self._next_table is None:
            if self.n <= NEXT_TABLE_LOAD * self.table.shape[0]:
                return
            self._next_table = np.empty(2 * self.table.shape[0], np.int32)  # address space, untouched
            self._next_cleared = self._next_filled = 0
        size = self._next_table.shape[0]
        if self._next_cleared < size:
            stop = min(size, self._next_cleared + int(NEXT_TABLE_CLEAR * size))
            self._next_table[self._next_cleared: stop] = -1
            self._next_cleared = stop
            return
        stop = min(self.n, self._next_filled + int(NEXT_TABLE_SLICE * size))
        insert_range_kernel(self._next_table, self.state["keys"], self._next_filled, stop)
        self._next_filled = stop
        if stop == self.n:
            self.table, self._next_table = self._next_table, None

    def rebuild_table(self) -> None:
        """Rehash the first `len(self)` voxels into the table (after their keys were replaced wholesale)."""
        self._next_table = None
        self.table.fill(-1)
        insert_range_kernel(self.table, self.state["keys"], 0, self.n)

    def truncate(self, n: int) -> None:
        """Drop the voxels from ``n`` on (the last ones folds created, for a roll-back): out of the
        table, the last entered first, which leaves it as entering the first ``n`` alone would (what
        `rebuild_table` gives, at the cost of the dropped voxels instead of the map's); their rows
        zeroed, as in a map that never held them; the boxes of the chunks from ``n``'s on rebuilt."""
        end = self.n
        if not 0 <= n <= end:
            raise ValueError(f"n: expected a voxel count in [0, {end}], got {n}")
        if n == end:
            return
        self._next_table = None  # its slices may hold dropped voxels: it starts again when due
        remove_range_kernel(self.table, self.state["keys"], n, end)
        for array in self.state.values():
            array[n:end] = 0
        self.n = n
        first = n // CHUNK
        self.chunk_lo[first:], self.chunk_hi[first:] = 0, 0
        update_chunk_boxes_kernel(self.state["keys"], first * CHUNK, n, self.chunk_lo, self.chunk_hi)

    def set_label_dim(self, label_dim: int) -> None:
        """Widen every row by the label columns (zero so far) once the first frame with labels arrives;
        or narrow them away again (0), where a fold that widened them is undone."""
        old = self.stored
        self.layout = VoxelRows(self.feature_dim, sh_sum_widths(self.sh_degree), label_dim)
        self.stored = StoredRows(self.layout)
        kept = {"rows": min(old.width, self.stored.width), "half": min(old.half_width, self.stored.half_width)}
        for name, width in kept.items():
            before = self._backing[name]
            after = self._reserve(self.capacity, before.shape[0], (name,))[name]
            after[: self.n, :width] = before[: self.n, :width]  # the label columns come last in both
            self._backing[name] = after
        self._provide(self.capacity)

    def commit(self, touched: np.ndarray, n_new: int) -> None:
        """After integration wrote rows ``touched`` (existing voxels, -1 entries ignored) and ``n_new``
        new voxels after the first `len(self)`: stamp them, extend the chunk boxes, count them in."""
        stamp = self._stamp()
        self.changed_at[touched[touched >= 0]] = stamp
        self.changed_at[self.n: self.n + n_new] = stamp
        update_chunk_boxes_kernel(self.state["keys"], self.n, self.n + n_new, self.chunk_lo, self.chunk_hi)
        self.n += n_new
        self._written = max(self._written, self.n)
        self._fill_next_table()

    def touch(self, rows: np.ndarray) -> None:  # rows: [M] int64 voxel indices below len(self)
        """Stamp voxels ``rows`` as changed (their rows were restored from elsewhere), so that a
        decode redoes them."""
        self.changed_at[rows] = self._stamp()

    def _stamp(self) -> int:
        """A fresh change stamp; the first of a new epoch restamps every voxel, whose stamps of the
        last epoch the new one may give again to other sums."""
        epoch, stamp = stamps.STAMPS.next()
        if epoch != self.stamp_epoch:
            self.changed_at[: self.n] = stamp
            self.stamp_epoch = epoch
        return stamp

    # -- reading ------------------------------------------------------------------------------
    def find(self, keys: np.ndarray) -> np.ndarray:  # [M] int64 keys -> [M] int32 voxel indices, -1 absent
        """The voxel indices of ``keys``."""
        keys = np.ascontiguousarray(keys, np.int64)
        out = np.empty(keys.shape[0], np.int32)
        lookup_kernel(self.table, self.state["keys"], keys, out)
        return out

    def representative_points(self, voxel_size: float, max_points: int = 20_000) -> np.ndarray | None:  # [<= ~max_points, 3]
        """Representative positions (world, float32) of an evenly strided subset of the voxels, for
        voxels of ``voxel_size`` (None when empty)."""
        if not self.n:
            return None
        step = max(1, self.n // max_points)
        cells = unpack_keys(torch.from_numpy(self.state["keys"][: self.n: step])).numpy()
        local = self.stored.field({"half": self.state["half"][: self.n: step]}, "rep_local").astype(np.float64)
        return ((cells + 0.5 + local) * voxel_size).astype(np.float32)

    def sums(self) -> dict[str, np.ndarray]:
        """The stored per-voxel sums (`stored`: contiguous copies, insertion order, spare rows excluded)."""
        return {name: array.copy() for name, array in self.sums_of(self.state).items()}

    def copied_state(self) -> dict[str, np.ndarray]:
        """A copy of the `len(self)` rows of `state`: one block copy per array, split between the
        numba threads (for `sums_of`; a snapshot's capture copies the whole state under the lock)."""
        out = {}
        for name, array in self.state.items():
            rows = array[: self.n]
            out[name] = np.empty_like(rows)
            copy_bytes(rows.reshape(-1).view(np.uint8), out[name].reshape(-1).view(np.uint8))
        return out

    def sums_of(self, state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The sums as views into ``state`` (the map's arrays or a copy of them), its first `len(self)` rows."""
        return sums_view(state, self.stored, self.n)

    def load_sums(self, sums: dict[str, np.ndarray]) -> None:
        """Inverse of `sums` on an empty map (snapshot loading): rows, hash table and chunk boxes.
        Float32 sums in place of the stored means (earlier snapshots) are stored as a fold stores them."""
        n = len(sums["keys"])
        self.reserve(n)
        for name in ARRAYS:
            self.state[name][:n] = sums[name]
        self.stored.from_sums(sums, self.state)
        self.n = n
        self._written = max(self._written, n)
        self.changed_at[:n] = self._stamp()
        self.rebuild_table()
        update_chunk_boxes_kernel(self.state["keys"], 0, n, self.chunk_lo, self.chunk_hi)

    def nbytes(self) -> int:
        """Bytes of memory the map holds: the rows of its blocks written so far (the rest of a block
        is address space the system has not backed), the hash table and the successor's cleared part."""
        successor = 0 if self._next_table is None else self._next_cleared * self._next_table.itemsize
        return int((self._row_bytes() + self.changed_at.itemsize) * self._written + self.table.nbytes + successor)

    def _row_bytes(self) -> int:
        return sum(a.itemsize * int(np.prod(a.shape[1:])) for a in self.state.values())

    def new_voxel_bytes(self) -> int:
        """Bytes one voxel added to the map can cost at most: its row of every per-voxel array, its
        change stamp, and `TABLE_SLOTS_PER_NEW_VOXEL` hash slots (a table just grown sits at half its
        largest load, and its successor fills beside it at twice its size)."""
        return self._row_bytes() + self.changed_at.itemsize + TABLE_SLOTS_PER_NEW_VOXEL * self.table.itemsize

    def bytes_per_voxel(self) -> float:
        """Bytes per stored voxel: one row of every per-voxel array plus the hash table's bytes per
        stored voxel."""
        return self._row_bytes() + self.table.nbytes / max(self.n, 1)
