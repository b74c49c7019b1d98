"""Per-voxel decode results kept between decodes, so that a decode after a fold redoes only the voxels
the fold touched.

A Gaussian's shape and colour (`GaussianDecoder.shapes_and_colours`) are functions of its own
voxel's sums; only its opacity depends on the scene as a whole (the support unit), and that is
cheap to recompute for every voxel. A fold changes the sums of the voxels its observations land in
(tens of thousands) while the scene holds hundreds of thousands, so the decoder side (`scene.decoding`) keeps each
decoded row here with the fold stamp of the sums it came from, and reuses it while the row's sums
still carry that stamp. Stamps are unique per fold within a stamp epoch (`stamps.StampClock`), so
equal stamps of one epoch mean equal sums; the decoder side starts new decoded rows in a new epoch.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from .half import from_half

# the parts of a decoded row that are kept, in `GaussianDecoder.shapes_and_colours`' names; the
# features (F_scene, 64 bytes a voxel at 16 channels) are recomputed from the sums instead
PARTS = ("means", "scales", "quats", "sh", "labels")
# the parts kept in float16 (a decode rounds them so, `rounded`, whether it reuses rows or not): a
# scale's or a colour coefficient's relative precision is all that matters of it, where the means
# are world positions, which float16 would put centimetres off a few metres from the origin
HALF_PARTS = ("scales", "quats", "sh")


def rounded(parts: dict[str, Tensor | None]) -> dict[str, Tensor | None]:
    """``parts`` with `HALF_PARTS` rounded to float16 (and back to float32): what the decoded rows
    keep of them, so a decode that reuses rows and one that does not give the same Gaussians."""
    return {k: v.half().float() if k in HALF_PARTS and v is not None else v for k, v in parts.items()}


@numba.njit(parallel=True, cache=True)
def _gather_kernel(source, rows, out):  # out[i] = source[rows[i]], [V, C] -> [N, C]
    for i in numba.prange(rows.shape[0]):
        for j in range(source.shape[1]):
            out[i, j] = source[rows[i], j]


@numba.njit(parallel=True, cache=True)
def _gather_widened_kernel(source, rows, out):  # out[i] = source[rows[i]] as float32: float16 bits [V, C] -> [N, C]
    for i in numba.prange(rows.shape[0]):
        for j in range(source.shape[1]):
            out[i, j] = from_half(source[rows[i], j])


def gather_rows(
    source: np.ndarray,  # [V] or [V, ...], e.g. a column of the scene's sums (often strided: a view of its rows)
    rows: np.ndarray,  # [N] int64
    widen: bool = False,  # float16 comes out as float32 (exactly: every float16 is a float32)
) -> torch.Tensor:  # [N] or [N, ...], contiguous
    """``source[rows]`` on the numba threads: over a strided view this is several times faster than
    torch's index_select or numpy's fancy indexing, which copy element by element, and over a
    contiguous one it still splits the copy between the threads. Float16 is copied as its bits
    (numba has no float16), or with ``widen`` converted to float32 in the same pass, which saves
    reading and writing the copy again to convert it."""
    dtype = source.dtype
    widened = widen and dtype == np.float16
    if dtype == np.float16:
        source = source.view(np.uint16)
    width = int(np.prod(source.shape[1:]))  # not -1: an empty scene's columns have no size to infer it from
    out = np.empty((len(rows), width), np.float32 if widened else source.dtype)
    if len(rows) and width:
        (_gather_widened_kernel if widened else _gather_kernel)(source.reshape(len(source), width), rows, out)
    return torch.from_numpy((out if widened else out.view(dtype)).reshape(len(rows), *source.shape[1:]))


@numba.njit(cache=True)
def _current_kernel(slot_of, slot_stamps, rows, stamps, out):
    for i in range(rows.shape[0]):
        slot = slot_of[rows[i]] if rows[i] < slot_of.shape[0] else -1
        out[i] = slot >= 0 and slot_stamps[slot] == stamps[i]


class DecodedRows:
    """Decoded shapes and colours by scene row, each with its sums' fold stamp.

    Results live in slots, one per row that was ever decoded (`slot_of`: a row's slot, -1 for none),
    so the rows that never decode (a third to a half of a scene: too little support, or seen
    through) cost 4 bytes each instead of a whole decoded row.

    ``key`` names what else the results depend on (the decoder's parameters, the label channels):
    a scene starts a new `DecodedRows` when it changes. Not locked itself: `scene.decoding.SceneDecoding`
    holds its lock around each use.

    Example:
        >>> rows = DecodedRows(key=0)
        >>> rows.store(np.array([0, 2]), np.array([5, 5], np.int32), {"means": torch.ones(2, 3), "labels": None})
        >>> rows.current(np.array([2, 0, 1]), np.array([5, 6, 5], np.int32)).tolist()
        [True, False, False]
        >>> rows.gather(np.array([2, 0]))["means"].shape
        torch.Size([2, 3])
    """

    def __init__(self, key):
        self.key = key
        self.slot_of = np.full(0, -1, np.int32)  # [rows seen] each row's slot, -1: none
        self.slots = 0  # slots in use
        self.stamps = np.full(0, -1, np.int32)  # [slot capacity] the stamp each slot was decoded from
        self._parts: dict[str, Tensor | None] = {}

    def current(
        self,
        rows: np.ndarray,  # [M] scene rows
        stamps: np.ndarray,  # [M] int32 the fold stamps of their current sums
    ) -> np.ndarray:  # [M] bool: decoded from these very sums
        hit = np.empty(len(rows), np.bool_)
        _current_kernel(self.slot_of, self.stamps, rows, stamps, hit)
        return hit

    def store(
        self,
        rows: np.ndarray,  # [M] scene rows
        stamps: np.ndarray,  # [M] int32 the fold stamps of the sums they were decoded from
        parts: dict[str, Tensor | None],  # name -> [M, ...] (or None for an absent part)
    ) -> None:
        if not len(rows):
            return
        size = int(rows.max()) + 1
        if size > len(self.slot_of):  # grow by half at least: a scene grows every fold
            grown = np.full(max(size, len(self.slot_of) * 3 // 2), -1, np.int32)
            grown[: len(self.slot_of)] = self.slot_of
            self.slot_of = grown
        new = rows[self.slot_of[rows] < 0]
        first = self.slots  # new rows take the next slots, in their order
        self.slot_of[new] = np.arange(first, first + len(new), dtype=np.int32)
        self.slots += len(new)
        if self.slots > len(self.stamps):
            capacity = max(self.slots, len(self.stamps) * 3 // 2)
            stamps_grown = np.full(capacity, -1, np.int32)
            stamps_grown[: len(self.stamps)] = self.stamps
            self.stamps = stamps_grown
            for name, part in parts.items():
                old = self._parts.get(name)
                if part is None:
                    self._parts[name] = None
                    continue
                dtype = torch.float16 if name in HALF_PARTS else part.dtype
                # slots past the old ones are written below before any is read (they are the new rows')
                grown_part = torch.empty((capacity, *part.shape[1:]), dtype=dtype)
                if old is not None:
                    grown_part[: len(old)] = old
                self._parts[name] = grown_part
        slots = self.slot_of[rows]
        run = len(new) == len(rows)  # all new (a decode from scratch): one run of slots, converted as copied
        index = None if run else torch.from_numpy(slots.astype(np.int64))
        for name, part in parts.items():
            if part is None:
                continue
            kept = self._parts[name]
            if run:
                kept[first: first + len(rows)].copy_(part.detach())
            else:
                kept.index_copy_(0, index, part.detach().to(kept.dtype))
        self.stamps[slots] = stamps

    def gather(self, rows: np.ndarray) -> dict[str, Tensor | None]:  # [M] rows -> name -> [M, ...] float32
        slots = self.slot_of[rows].astype(np.int64)
        return {name: None if part is None else gather_rows(part.numpy(), slots, widen=True).float()
                for name, part in self._parts.items()}

    def nbytes(self) -> int:
        return int(self.slot_of.nbytes + self.stamps.nbytes
                   + sum(p.numel() * p.element_size() for p in self._parts.values() if p is not None))
