"""How the voxel map stores each voxel's record: float32 where precision matters, float16 elsewhere.

The fold works on the full float32 record (`kernels.VoxelRows`: the representative and its
weighted sums). Stored that way it is the bulk of a scene's memory, so the map keeps it in two
arrays instead:

- ``rows`` [V, width] float32: the representative's reliability, R_scene and the label weight;
- ``half`` [V, half_width] uint16 columns: every other field, as a quantity that stays within its
  inputs' range however long the stream:
  - the representative's feature as its direction, 8 bits a channel (two channels a column, the
    direction scaled so that its largest channel is +-127, and rounded: ``rep_dir``). Only its direction enters the fold
    (the similarity weight is a cosine), and 8 bits move a cosine by about a hundredth at most;
  - in float16 (held as its bits, `half`), where float16 keeps about 3.3 significant digits:
    the representative's position in local voxel units (``rep_local``: its offset from the voxel's
    centre, within 1/2, which float16 holds to 1/8000 of a voxel);
    a first moment as its *mean* over R_scene (``f_mean``, ``rgb_mean``, ``pos_mean``, and the
    label scores' ``label_mean``, whose channels take a float a voxel each; a sum grows without
    bound, and float16 ends at 65504);
    a second moment as its *central* moment over R_scene, about the stored means (``pos_cov``, and
    the SH fit's normal equations ``sh_a_central``, ``sh_b_central``). A raw second moment is a
    difference away from what its readers need: the covariance E[x x^T] - E[x] E[x]^T, and the SH
    fit's view-dependent terms, whose normal equations reduce to the central moments of the view
    basis. Where the points or the view directions spread little, that difference cancels most of
    the raw moment, and float16's rounding of it would be amplified; the central moment is stored
    at float16's relative precision of itself.

    A representative's replacement rescales every sum and R_scene alike, so it leaves means and
    central moments as they were.

The fold kernel loads each touched voxel's stored record into a float32 working record
(`load_row`: the direction as its 8-bit values, means times R_scene, central moments plus the
product of their means, times R_scene),
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
    >>> stored.width, stored.half_width  # 4 feature channels: 2 columns of direction
    (2, 39)
    >>> sorted(n for n, c in stored.columns.items() if c[0] == "half")
    ['f_mean', 'pos_cov', 'pos_mean', 'rep_dir', 'rep_local', 'rgb_mean', 'sh_a_central', 'sh_b_central']
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numba
import numpy as np

from ..gaussians.container import SH_C0
from .half import from_half, to_half

if TYPE_CHECKING:
    from .kernels import VoxelRows

# how a float16 column is stored: as it is, as a mean over R_scene, or as a central moment over R_scene
AS_IS, MEAN, CENTRAL = 0, 1, 2
# the working record's fields kept in float16: name -> stored name
HALF_FIELDS = {"rep_pos": "rep_local", "f_sum": "f_mean", "rgb_sum": "rgb_mean", "pos_sum": "pos_mean",
               "pos_sq": "pos_cov", "sh_a": "sh_a_central", "sh_b": "sh_b_central", "label_sum": "label_mean"}
SUMS = {stored: name for name, stored in HALF_FIELDS.items()}  # stored name -> its sum's name
DIRECTION_STEPS = 127  # the stored direction's largest channel: its channels are then int8
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
    if name == "rep_pos":  # in local voxel units, within the voxel: float16 as it is
        return [(AS_IS, None, None)] * width
    if name in ("f_sum", "rgb_sum", "pos_sum", "label_sum"):
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
    field's name to (array name, first column, field shape); ``wide_cols`` [width] are the working
    record's column of each float32 column. The ``half`` array holds the representative's direction
    first (``direction``: its first working column, its channels and the columns they take), then the
    float16 columns: ``half_cols`` [H] are their working columns and, for the kernels, ``half_kind``
    [H] how each is stored (AS_IS, MEAN or CENTRAL), and for a central moment its two means,
    ``factor_cols`` [H, 4] int64 (their ``half`` columns, then their working columns) and
    ``factor_affine`` [H, 4] float32 (scale and offset of each)."""

    def __init__(self, layout: VoxelRows):
        self.layout = layout
        first, (channels,) = layout.columns["rep_f"]
        pairs = (channels + 1) // 2
        self.direction = np.array([first, channels, pairs], np.int64)
        self.columns: dict[str, tuple[str, int, tuple[int, ...]]] = {"rep_dir": ("half", 0, (channels,))}
        bases = sh_bases(layout.columns["sh_a"][1][0])
        wide, half, rules = [], [], []
        for name, (first, shape) in layout.columns.items():
            cols = list(range(first, first + (shape[0] if shape else 1)))
            if name in HALF_FIELDS:
                self.columns[HALF_FIELDS[name]] = ("half", pairs + len(half), shape)
                half += cols
                rules += column_rules(name, len(cols), bases)
            elif name != "rep_f":
                self.columns[name] = ("rows", len(wide), shape)
                wide += cols
        self.wide_cols, self.half_cols = np.array(wide, np.int64), np.array(half, np.int64)
        self.width, self.half_width = len(wide), pairs + len(half)
        self.half_kind = np.array([kind for kind, _, _ in rules], np.int64)
        self.factor_cols = np.zeros((len(half), 4), np.int64)
        self.factor_affine = np.zeros((len(half), 4), np.float32)
        for c, (kind, a, b) in enumerate(rules):
            if kind == CENTRAL:
                work = [layout.columns[f.field][0] + f.column for f in (a, b)]
                self.factor_cols[c] = [pairs + half.index(work[0]), pairs + half.index(work[1]), *work]
                self.factor_affine[c] = [a.scale, a.offset, b.scale, b.offset]

    def field(self, state: dict[str, np.ndarray], name: str) -> np.ndarray:
        """View of one stored field of ``state``'s ``rows`` / ``half`` ([V] or [V, n]; float16 for
        the moments, int8 for the direction)."""
        array, first, shape = self.columns[name]
        if name == "rep_dir":
            pairs = int(self.direction[2])
            return state["half"][:, :pairs].view(np.int8)[:, : shape[0]]
        block = state[array] if array == "rows" else state[array].view(np.float16)
        return block[:, first] if not shape else block[:, first: first + shape[0]]

    def from_sums(self, sums: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> None:
        """Write ``sums`` (stored fields, or float32 sums as earlier snapshots hold them, [n, ...]) into
        the first n rows of ``out``'s ``rows`` and ``half``. A float32 sum is stored as `store_row`
        stores it: divided by R_scene in float32 (0 where R_scene is not positive), a central moment
        less the product of its unrounded means, then rounded; a representative's feature
        (``rep_f``) as its direction."""
        n = len(sums["r_sum"])
        rows = {k: v[:n] for k, v in out.items()}
        self.field(rows, "rep_dir")[...] = sums["rep_dir"] if "rep_dir" in sums else directions_of(sums["rep_f"])
        bases = sh_bases(self.layout.columns["sh_a"][1][0])
        r = np.asarray(sums["r_sum"], np.float32)[:, None]
        positive = r > 0
        safe = np.where(positive, r, np.float32(1))

        def mean(f: Factor) -> np.ndarray:
            return (np.asarray(sums[f.field], np.float32)[:, f.column] / safe[:, 0]) * np.float32(f.scale) + np.float32(f.offset)

        for name in self.columns.keys() - {"rep_dir"}:
            value = sums.get(name)
            if value is None and name in SUMS:
                raw = np.asarray(sums[SUMS[name]], np.float32)
                value = raw.copy()
                for c, (kind, a, b) in enumerate(column_rules(SUMS[name], raw.shape[1], bases)):
                    if kind != AS_IS:
                        value[:, c] = np.where(positive[:, 0], raw[:, c] / safe[:, 0], np.float32(0))
                    if kind == CENTRAL:
                        value[:, c] = np.where(positive[:, 0], value[:, c] - mean(a) * mean(b), np.float32(0))
            self.field(rows, name)[...] = value


def raw_sums(stored: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A scene's stored fields (`StoredRows.field` views or copies, [V, ...]) with the float16 means
    and central moments present turned back into their float32 sums, as `load_row` computes them:
    ``mean * R_scene``, ``(central + mean_a * mean_b) * R_scene``; the stored direction as the
    representative's feature (``rep_f``, its 8-bit values) and its local position as ``rep_pos``.
    Other fields pass unchanged, float32 sums too (the batch reference's, earlier snapshots'). Each
    field is one pass on the numba threads, reading the float16 columns where they are."""
    out = dict(stored)
    if "rep_dir" in out:
        out["rep_f"] = out.pop("rep_dir").astype(np.float32)
    present = [name for name in SUMS if name in stored]
    if not present:
        return out
    r = np.ascontiguousarray(stored["r_sum"], np.float32)
    bases = sh_bases(stored["sh_a_central"].shape[1] if "sh_a_central" in stored else 0)
    for name in present:
        value = np.empty((len(r), stored[name].shape[1]), np.float32)
        if len(r) and value.shape[1]:
            _raw_sums_kernel(sum_rules(stored, name, bases), r, value)
        out[SUMS[name]] = value
        del out[name]
    return out


def sum_rules(stored: dict[str, np.ndarray], name: str, bases: int) -> tuple[np.ndarray, ...]:
    """How `raw_sum` makes the float32 sums of the stored field ``name`` of ``stored`` (``bases``: K,
    `sh_bases`), as a tuple a numba kernel takes: (its float16 bits [V, W], each column's kind [W]
    (AS_IS, MEAN or CENTRAL), the float16 bits of the stored means a central moment's two factors
    read [V, *] (a field's central moments take theirs from one stored field each), the factors'
    columns in them [W, 2], their float32 scales and offsets [W, 4])."""
    x = stored[name]
    rules = column_rules(SUMS[name], x.shape[1], bases)
    kinds = np.array([kind for kind, _, _ in rules], np.int64)
    cols, affine = np.zeros((len(rules), 2), np.int64), np.zeros((len(rules), 4), np.float32)
    a_source = b_source = x
    for c, (kind, a, b) in enumerate(rules):
        if kind == CENTRAL:
            a_source, b_source = stored[HALF_FIELDS[a.field]], stored[HALF_FIELDS[b.field]]
            cols[c], affine[c] = (a.column, b.column), (a.scale, a.offset, b.scale, b.offset)
    return x.view(np.uint16), kinds, a_source.view(np.uint16), b_source.view(np.uint16), cols, affine


@numba.njit(inline="always")
def raw_sum(rules, v, c, r):
    """The float32 sum of column ``c`` of voxel ``v`` of a stored field (`sum_rules`; R_scene ``r``)."""
    x, kinds, a_source, b_source, cols, affine = rules
    return sum_of(from_half(x[v, c]), kinds[c], factor(a_source, v, cols[c, 0], affine[c, 0], affine[c, 1]),
                  factor(b_source, v, cols[c, 1], affine[c, 2], affine[c, 3]), r)


@numba.njit(parallel=True, cache=True)
def _raw_sums_kernel(
    rules,  # `sum_rules` of one stored field, [V, W]
    r,  # [V] float32 R_scene
    out,  # [V, W] float32
):
    for v in numba.prange(out.shape[0]):
        for c in range(out.shape[1]):
            out[v, c] = raw_sum(rules, v, c, r[v])


@numba.njit(inline="always")
def _signed(byte):  # the int8 whose bits are ``byte`` (0..255)
    return byte - 256 if byte > 127 else byte


@numba.njit(inline="always")
def quantize_direction(x, first, channels):
    """``x[first: first + channels]``, in place, as the stored direction: scaled so that its largest
    channel is +-`DIRECTION_STEPS` (the whole int8 range for every vector) and rounded to integers
    (a zero vector stays zero). The fold applies it to a representative as it is chosen, so that
    what it folds against is what the map keeps."""
    largest = np.float32(0.0)
    for c in range(channels):
        largest = max(largest, abs(x[first + c]))
    scale = np.float32(DIRECTION_STEPS) / largest if largest > np.float32(1e-30) else np.float32(0.0)
    for c in range(channels):
        q = np.floor(x[first + c] * scale + np.float32(0.5))
        x[first + c] = min(np.float32(DIRECTION_STEPS), max(np.float32(-DIRECTION_STEPS), q))


@numba.njit(inline="always")
def _pack_direction(x, first, channels, half, v):  # a quantized direction's integers, two 8-bit values a column
    for p in range((channels + 1) // 2):
        bits = 0
        for k in range(2):
            c = 2 * p + k
            if c < channels:
                bits |= (int(x[first + c]) & 0xFF) << (8 * k)
        half[v, p] = bits


@numba.njit(cache=True)
def _directions_kernel(
    features: np.ndarray,  # [n, L] float32, a copy: quantized in place
    half: np.ndarray,  # [>= n, half_width] uint16: the direction's columns are written
) -> None:
    for i in range(features.shape[0]):
        quantize_direction(features[i], 0, features.shape[1])
        _pack_direction(features[i], 0, features.shape[1], half, i)


def directions_of(features: np.ndarray) -> np.ndarray:  # [n, L] float -> [n, L] int8
    """The stored direction of each feature (`quantize_direction`)."""
    features = np.array(features, np.float32)  # a copy, quantized in place
    channels = features.shape[1]
    half = np.zeros((len(features), (channels + 1) // 2), np.uint16)
    _directions_kernel(features, half)
    return half.view(np.int8)[:, :channels].copy()


@numba.njit(inline="always")
def factor(half, v, column, scale, offset):  # a stored mean, scaled and offset as a central moment takes it
    return from_half(half[v, column]) * scale + offset


@numba.njit(inline="always")
def sum_of(stored, kind, factor_a, factor_b, r):
    """The float32 sum of one stored float16 value (as a float32) of ``kind``: as it is, a mean
    times R_scene ``r``, or a central moment plus the product of its two means (``factor``), times
    ``r``. Every reader of the stored moments makes its sums here, so they agree bit for bit."""
    if kind == CENTRAL:
        stored = stored + factor_a * factor_b
    return stored if kind == AS_IS else stored * r


@numba.njit(inline="always")
def load_row(rows, half, v, wide_cols, direction, half_cols, half_kind, factor_cols, factor_affine, r_col, work):
    """Voxel ``v``'s stored record into the float32 working record ``work``: the direction as its
    8-bit values, means become sums again (times R_scene), central moments raw second moments (plus
    the product of their stored means, times R_scene)."""
    for c in range(wide_cols.shape[0]):
        work[wide_cols[c]] = rows[v, c]
    first, channels = direction[0], direction[1]
    for c in range(channels):
        work[first + c] = np.float32(_signed((half[v, c // 2] >> (8 * (c % 2))) & 0xFF))
    r = work[r_col]
    pairs = direction[2]
    for c in range(half_cols.shape[0]):
        work[half_cols[c]] = sum_of(from_half(half[v, pairs + c]), half_kind[c],
                                    factor(half, v, factor_cols[c, 0], factor_affine[c, 0], factor_affine[c, 1]),
                                    factor(half, v, factor_cols[c, 1], factor_affine[c, 2], factor_affine[c, 3]), r)


@numba.njit(inline="always")
def store_row(work, rows, half, v, wide_cols, direction, half_cols, half_kind, factor_cols, factor_affine, r_col):
    """`load_row` inverted: the working record into voxel ``v``'s stored one (its direction already
    quantized: `quantize_direction`; 0 for the means and central moments where R_scene is not
    positive), rounded to float16. A central moment is taken about the float32 means, before they
    are rounded."""
    for c in range(wide_cols.shape[0]):
        rows[v, c] = work[wide_cols[c]]
    _pack_direction(work, direction[0], direction[1], half, v)
    r = work[r_col]
    pairs = direction[2]
    for c in range(half_cols.shape[0]):
        value = np.float32(0.0)
        if half_kind[c] == AS_IS:
            value = work[half_cols[c]]
        elif r > np.float32(0.0):
            value = work[half_cols[c]] / r
            if half_kind[c] == CENTRAL:
                a = (work[factor_cols[c, 2]] / r) * factor_affine[c, 0] + factor_affine[c, 1]
                b = (work[factor_cols[c, 3]] / r) * factor_affine[c, 2] + factor_affine[c, 3]
                value = value - a * b
        half[v, pairs + c] = to_half(value)
