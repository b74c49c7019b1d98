"""How the voxel map stores each voxel's record: float32 where precision matters, float16 elsewhere.

The fold works on the full float32 record (`kernels.VoxelRows`: the representative and its
weighted sums). Stored that way it is the bulk of a scene's memory, so the map keeps it in two
arrays instead:

- ``rows`` [V, width] float32: the representative's reliability and position, R_scene and the
  label sums;
- ``half`` [V, half_width] float16 (held as uint16 bits, `half`): every other field, as a quantity
  that stays within its inputs' range however long the stream, where float16 keeps about 3.3
  significant digits:
  - the representative's feature as it is;
  - a first moment as its *mean* over R_scene (``f_mean``, ``rgb_mean``, ``pos_mean``; a sum grows
    without bound, and float16 ends at 65504);
  - a second moment as its *central* moment over R_scene, about the stored means (``pos_cov``, and
    the SH fit's normal equations ``sh_a_central``, ``sh_b_central``). A raw second moment is a
    difference away from what its readers need: the covariance E[x x^T] - E[x] E[x]^T, and the SH
    fit's view-dependent terms, whose normal equations reduce to the central moments of the view
    basis. Where the points or the view directions spread little, that difference cancels most of
    the raw moment, and float16's rounding of it would be amplified; the central moment is stored
    at float16's relative precision of itself.

  A representative's replacement rescales every sum and R_scene alike, so it leaves means and
  central moments as they were.

The fold kernel loads each touched voxel's stored record into a float32 working record
(`load_row`: means times R_scene, central moments plus the product of their means, times R_scene),
folds into that, and stores it back (`store_row`: the central moments about the float32 means
before they are rounded). Everything else reads the stored fields as views (`StoredRows.field`), the
float16 ones through numpy's float16, and `raw_sums` turns them back into the float32 sums the
fields are defined on (`fields.fields_from_sums`), in the kernel's order of operations, so that the
two agree bit for bit.

The SH sums' layout (`fields.sh_sum_widths`): ``sh_a`` is the upper triangle of sum W b b^T without
its (0, 0) entry; its first row, sum W Y_0 b_k = Y_0 sum W b_k (Y_0 = C0 for every observation), is
stored as a mean, the rest (k, l >= 1) as central moments about the means of b_k and b_l; ``sh_b``,
sum W b_k (c - 1/2), as central moments about the means of b_k and of c - 1/2.

Example:
    >>> from canonical_core.scene.kernels import VoxelRows
    >>> stored = StoredRows(VoxelRows(feature_dim=4, sh_widths=(9, 9)))
    >>> stored.width, stored.half_width
    (5, 38)
    >>> sorted(n for n, c in stored.columns.items() if c[0] == "half")
    ['f_mean', 'pos_cov', 'pos_mean', 'rep_f', 'rgb_mean', 'sh_a_central', 'sh_b_central']
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numba
import numpy as np

from ..gaussians.container import SH_C0
from .half import from_half, to_half

if TYPE_CHECKING:
    from .kernels import VoxelRows

# how a float16 column is stored: as it is, as a mean over R_scene, as a central moment over R_scene
AS_IS, MEAN, CENTRAL = 0, 1, 2
# the working record's fields kept in float16: name -> stored name
HALF_FIELDS = {"rep_f": "rep_f", "f_sum": "f_mean", "rgb_sum": "rgb_mean", "pos_sum": "pos_mean",
               "pos_sq": "pos_cov", "sh_a": "sh_a_central", "sh_b": "sh_b_central"}
SUMS = {stored: name for name, stored in HALF_FIELDS.items() if stored != name}  # stored name -> its sum's name
_SQ_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # pos_sq's columns xx xy xz yy yz zz


class Factor(NamedTuple):
    """One of the two means a central moment is about: ``scale * (sum[column] / R_scene) + offset``,
    ``sum`` the working record's field ``field`` (itself stored as a mean)."""

    field: str
    column: int
    scale: float
    offset: float


def column_rules(name: str, width: int, bases: int) -> list[tuple[int, Factor | None, Factor | None]]:
    """How each of the ``width`` columns of the working record's field ``name`` is stored in float16
    (``bases``: K, the SH bases of the fit): (AS_IS, MEAN or CENTRAL, and for CENTRAL the two means
    it is about)."""
    if name == "rep_f":
        return [(AS_IS, None, None)] * width
    if name in ("f_sum", "rgb_sum", "pos_sum"):
        return [(MEAN, None, None)] * width
    if name == "pos_sq":
        return [(CENTRAL, Factor("pos_sum", a, 1.0, 0.0), Factor("pos_sum", b, 1.0, 0.0)) for a, b in _SQ_PAIRS]

    def basis(k: int) -> Factor:  # the mean of b_k: sh_a's first row holds sum W C0 b_k
        return Factor("sh_a", k - 1, 1.0 / SH_C0, 0.0)

    if name == "sh_a":
        return [(MEAN, None, None) if p == 0 else (CENTRAL, basis(p), basis(q))
                for p in range(bases) for q in range(p, bases) if p or q]
    if name == "sh_b":  # sum W b_k (c - 1/2): about the means of b_k and of c - 1/2
        return [(CENTRAL, basis(k), Factor("rgb_sum", c, 1.0, -0.5)) for k in range(1, bases) for c in range(3)]
    raise KeyError(name)


def sh_bases(sh_a_width: int) -> int:
    """K, the SH bases, of an ``sh_a`` of ``sh_a_width`` = K (K + 1) / 2 - 1 columns."""
    k = 1
    while k * (k + 1) // 2 - 1 < sh_a_width:
        k += 1
    return k


class StoredRows:
    """The stored layout of a `VoxelRows` record (see the module): ``columns`` maps each stored
    field's name to (array name, first column, field shape); ``wide_cols`` [width] and
    ``half_cols`` [half_width] are the working record's column of each stored column. For the
    kernels, per float16 column: ``half_kind`` [half_width] (AS_IS, MEAN, CENTRAL), and for a
    central moment its two means, ``factor_cols`` [half_width, 4] int64 (their float16 columns, then
    their working-record columns) and ``factor_affine`` [half_width, 4] float32 (scale and offset of
    each)."""

    def __init__(self, layout: VoxelRows):
        self.layout = layout
        self.columns: dict[str, tuple[str, int, tuple[int, ...]]] = {}
        bases = sh_bases(layout.columns["sh_a"][1][0])
        wide, half, rules = [], [], []
        for name, (first, shape) in layout.columns.items():
            cols = list(range(first, first + (shape[0] if shape else 1)))
            if name in HALF_FIELDS:
                self.columns[HALF_FIELDS[name]] = ("half", len(half), shape)
                half += cols
                rules += column_rules(name, len(cols), bases)
            else:
                self.columns[name] = ("rows", len(wide), shape)
                wide += cols
        self.wide_cols, self.half_cols = np.array(wide, np.int64), np.array(half, np.int64)
        self.width, self.half_width = len(wide), len(half)
        self.half_kind = np.array([kind for kind, _, _ in rules], np.int64)
        self.factor_cols = np.zeros((len(half), 4), np.int64)
        self.factor_affine = np.zeros((len(half), 4), np.float32)
        for c, (kind, a, b) in enumerate(rules):
            if kind == CENTRAL:
                work = [layout.columns[f.field][0] + f.column for f in (a, b)]
                self.factor_cols[c] = [half.index(work[0]), half.index(work[1]), *work]
                self.factor_affine[c] = [a.scale, a.offset, b.scale, b.offset]

    def field(self, state: dict[str, np.ndarray], name: str) -> np.ndarray:
        """View of one stored field of ``state``'s ``rows`` / ``half`` ([V] or [V, n]; float16 for
        the half columns)."""
        array, first, shape = self.columns[name]
        block = state[array] if array == "rows" else state[array].view(np.float16)
        return block[:, first] if not shape else block[:, first: first + shape[0]]

    def from_sums(self, sums: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> None:
        """Write ``sums`` (stored fields, or float32 sums as earlier snapshots hold them, [n, ...]) into
        the first n rows of ``out``'s ``rows`` and ``half``. A float32 sum is stored as `store_row`
        stores it: divided by R_scene in float32 (0 where R_scene is not positive), a central moment
        less the product of its unrounded means, then rounded."""
        n = len(sums["r_sum"])
        bases = sh_bases(self.layout.columns["sh_a"][1][0])
        r = np.asarray(sums["r_sum"], np.float32)[:, None]
        positive = r > 0
        safe = np.where(positive, r, np.float32(1))

        def mean(f: Factor) -> np.ndarray:
            return (np.asarray(sums[f.field], np.float32)[:, f.column] / safe[:, 0]) * np.float32(f.scale) + np.float32(f.offset)

        for name in self.columns:
            value = sums.get(name)
            if value is None and name in SUMS:
                raw = np.asarray(sums[SUMS[name]], np.float32)
                value = raw / safe
                for c, (kind, a, b) in enumerate(column_rules(SUMS[name], raw.shape[1], bases)):
                    if kind == CENTRAL:
                        value[:, c] = value[:, c] - mean(a) * mean(b)
                value = np.where(positive, value, np.float32(0))
            self.field({k: v[:n] for k, v in out.items()}, name)[...] = value


def raw_sums(stored: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A scene's stored fields (`StoredRows.field` views or copies, [V, ...]) with the float16 means
    and central moments present turned back into their float32 sums, as `load_row` computes them:
    ``mean * R_scene``, ``(central + mean_a * mean_b) * R_scene``. Other fields pass unchanged,
    float32 sums too (the batch reference's, earlier snapshots')."""
    out = dict(stored)
    present = [name for name in SUMS if name in stored]
    if not present:
        return out
    r = np.asarray(stored["r_sum"], np.float32)[:, None]
    widths = {name: stored[name].shape[1] for name in present}
    bases = sh_bases(widths.get("sh_a_central", 0))

    def mean(f: Factor) -> np.ndarray:
        m = stored[HALF_FIELDS[f.field]][:, f.column].astype(np.float32)
        return m * np.float32(f.scale) + np.float32(f.offset)

    for name in present:
        value = stored[name].astype(np.float32)
        for c, (kind, a, b) in enumerate(column_rules(SUMS[name], widths[name], bases)):
            if kind == CENTRAL:
                value[:, c] = value[:, c] + mean(a) * mean(b)
        out[SUMS[name]] = value * r
        del out[name]
    return out


@numba.njit(inline="always")
def _factor(half, v, column, scale, offset):  # a stored mean, scaled and offset as a central moment takes it
    return from_half(half[v, column]) * scale + offset


@numba.njit(inline="always")
def load_row(rows, half, v, wide_cols, half_cols, half_kind, factor_cols, factor_affine, r_col, work):
    """Voxel ``v``'s stored record into the float32 working record ``work``: means become sums again
    (times R_scene), central moments raw second moments (plus the product of their stored means,
    times R_scene)."""
    for c in range(wide_cols.shape[0]):
        work[wide_cols[c]] = rows[v, c]
    r = work[r_col]
    for c in range(half_cols.shape[0]):
        value = from_half(half[v, c])
        kind = half_kind[c]
        if kind == CENTRAL:
            value = value + (_factor(half, v, factor_cols[c, 0], factor_affine[c, 0], factor_affine[c, 1])
                             * _factor(half, v, factor_cols[c, 1], factor_affine[c, 2], factor_affine[c, 3]))
        work[half_cols[c]] = value if kind == AS_IS else value * r


@numba.njit(inline="always")
def store_row(work, rows, half, v, wide_cols, half_cols, half_kind, factor_cols, factor_affine, r_col):
    """`load_row` inverted: the working record into voxel ``v``'s stored one (0 for the means and
    central moments where R_scene is not positive), rounded to float16. A central moment is taken
    about the float32 means, before they are rounded."""
    for c in range(wide_cols.shape[0]):
        rows[v, c] = work[wide_cols[c]]
    r = work[r_col]
    for c in range(half_cols.shape[0]):
        value = work[half_cols[c]]
        kind = half_kind[c]
        if kind != AS_IS:
            if r > np.float32(0.0):
                value = value / r
                if kind == CENTRAL:
                    a = (work[factor_cols[c, 2]] / r) * factor_affine[c, 0] + factor_affine[c, 1]
                    b = (work[factor_cols[c, 3]] / r) * factor_affine[c, 2] + factor_affine[c, 3]
                    value = value - a * b
            else:
                value = np.float32(0.0)
        half[v, c] = to_half(value)
