"""How the voxel map stores each voxel's record: float32 where precision matters, float16 elsewhere.

The fold works on the full float32 record (`kernels.VoxelRows`: the representative and its
weighted sums). Stored that way it is the bulk of a scene's memory, so the map keeps it in two
arrays instead:

- ``rows`` [V, width] float32: the representative's reliability and position, R_scene, the colour
  and position moments, the SH fit's normal equations, the label sums;
- ``half`` [V, half_width] float16 (held as uint16 bits, `half`): the representative's feature as
  it is, and the feature sum as its mean over R_scene. A sum grows without bound on a long stream
  (float16 ends at 65504); its mean stays within its inputs' range, where float16 keeps about 3.3
  significant digits. A representative's replacement rescales every sum and R_scene alike, so it
  leaves the mean as it was. The SH normal equations stay float32: their solve amplifies float16's
  rounding where the views leave a direction weakly determined (`tests/scene/test_sh_fit.py`).

The fold kernel loads each touched voxel's stored record into a float32 working record
(`load_row`), folds into that, and stores it back (`store_row`); everything else reads the stored
fields as views (`StoredRows.field`), the float16 ones through numpy's float16. The sums a scene
reports (`VoxelMap.sums`) are these stored fields; `fields.fields_from_sums` turns means back into
sums (``mean * R_scene``, in float32, as the kernel does).

Example:
    >>> from canonical_core.scene.kernels import VoxelRows
    >>> stored = StoredRows(VoxelRows(feature_dim=4, sh_widths=(9, 9)))
    >>> stored.width, stored.half_width, sorted(n for n, c in stored.columns.items() if c[0] == "half")
    (35, 8, ['f_mean', 'rep_f'])
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np

from .half import from_half, to_half

if TYPE_CHECKING:
    from .kernels import VoxelRows

# the working record's fields kept in float16: name -> (stored name, stored as its mean over R_scene)
HALF_FIELDS = {"rep_f": ("rep_f", False), "f_sum": ("f_mean", True)}
MEANS = {stored: name for name, (stored, mean) in HALF_FIELDS.items() if mean}  # stored mean -> its sum's name


class StoredRows:
    """The stored layout of a `VoxelRows` record (see the module): ``columns`` maps each stored
    field's name to (array name, first column, field shape); ``wide_cols`` [width] and
    ``half_cols`` [half_width] are the working record's column of each stored column, and
    ``half_mean`` [half_width] whether a float16 column holds a mean (for the kernels)."""

    def __init__(self, layout: VoxelRows):
        self.layout = layout
        self.columns: dict[str, tuple[str, int, tuple[int, ...]]] = {}
        wide, half, mean = [], [], []
        for name, (first, shape) in layout.columns.items():
            cols = list(range(first, first + (shape[0] if shape else 1)))
            if name in HALF_FIELDS:
                stored, is_mean = HALF_FIELDS[name]
                self.columns[stored] = ("half", len(half), shape)
                half += cols
                mean += [is_mean] * len(cols)
            else:
                self.columns[name] = ("rows", len(wide), shape)
                wide += cols
        self.wide_cols, self.half_cols = np.array(wide, np.int64), np.array(half, np.int64)
        self.half_mean = np.array(mean, np.bool_)
        self.width, self.half_width = len(wide), len(half)

    def field(self, state: dict[str, np.ndarray], name: str) -> np.ndarray:
        """View of one stored field of ``state``'s ``rows`` / ``half`` ([V] or [V, n]; float16 for
        the half columns)."""
        array, first, shape = self.columns[name]
        block = state[array] if array == "rows" else state[array].view(np.float16)
        return block[:, first] if not shape else block[:, first: first + shape[0]]

    def from_sums(self, sums: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> None:
        """Write ``sums`` (stored fields, or float32 sums as earlier snapshots hold them, [n, ...]) into
        the first n rows of ``out``'s ``rows`` and ``half``. A sum becomes its mean as `store_row`
        makes it: divided by R_scene in float32 (0 where R_scene is not positive), then rounded."""
        n = len(sums["r_sum"])
        for name in self.columns:
            value = sums.get(name)
            if value is None and name in MEANS:
                r = np.asarray(sums["r_sum"], np.float32)[:, None]
                with np.errstate(divide="ignore", invalid="ignore"):
                    value = np.where(r > 0, np.asarray(sums[MEANS[name]], np.float32) / r, np.float32(0))
            self.field({k: v[:n] for k, v in out.items()}, name)[...] = value


@numba.njit(inline="always")
def load_row(rows, half, v, wide_cols, half_cols, half_mean, r_col, work):
    """Voxel ``v``'s stored record into the float32 working record ``work``; means become sums again
    (times R_scene)."""
    for c in range(wide_cols.shape[0]):
        work[wide_cols[c]] = rows[v, c]
    r = work[r_col]
    for c in range(half_cols.shape[0]):
        value = from_half(half[v, c])
        work[half_cols[c]] = value * r if half_mean[c] else value


@numba.njit(inline="always")
def store_row(work, rows, half, v, wide_cols, half_cols, half_mean, r_col):
    """`load_row` inverted: the working record into voxel ``v``'s stored one, sums as means (0 where
    R_scene is not positive), rounded to float16."""
    for c in range(wide_cols.shape[0]):
        rows[v, c] = work[wide_cols[c]]
    r = work[r_col]
    for c in range(half_cols.shape[0]):
        value = work[half_cols[c]]
        if half_mean[c]:
            value = value / r if r > np.float32(0.0) else np.float32(0.0)
        half[v, c] = to_half(value)
