"""Whether a stream's depth agrees with itself, band by band of depth: how a session finds depth that a
sensor reports below its working range.

Structured-light and stereo sensors return, close to the camera, depth that is locally smooth and
looks like a surface but lands somewhere else in every frame (`docs/experiments.md`, "The labels
bin's near-range depth"). No single frame shows it; consecutive frames do. Each frame's depth, on a
grid of every `STRIDE`-th pixel, is lifted into the previous frame's camera and compared with that
frame's depth where it measured one: the two agree within max(`AGREE_M`, `AGREE_REL` x depth).
The comparisons are counted per band of the new frame's depth (`band_of`: bands from `BAND_START`
metres, each 2^(1/4) times as deep as the last). `inconsistent_below` reads the depth under which
every band with enough comparisons disagrees while every such band beyond it agrees: the sensor's
readings there are not of this scene, and the session's `near` setting can drop them. The check
only advises (a fold warning, and the limit in the session's stats); it changes nothing in the
scene. Its counts describe the sensor, so a snapshot keeps them and a rollback leaves them.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ..camera import Camera
from ..frame import Frame

STRIDE = 4  # every 4th pixel of every 4th row: the statistic needs hundreds of pixels a band, not all
AGREE_M, AGREE_REL = 0.01, 0.03  # agreement: within 1 cm or 3 % of the depth, whichever is larger
BAND_START, BANDS = 0.05, 40  # bands from 5 cm, each 2^(1/4) (about 19 %) wide, up to 51 m
_Q1, _Q2, _Q3 = 2.0 ** 0.25, 2.0 ** 0.5, 2.0 ** 0.75
MIN_COMPARED = 400  # comparisons before a band's agreement counts
DISAGREES, AGREES = 0.3, 0.7  # a band whose frames agree for less / at least this share
WARN_SHARE = 0.01  # a frame with at least this share of its depth in disagreeing bands is warned about


@numba.njit(cache=True)
def _band(depth, start, bands):
    # floor(4 log2(depth / start)) from the float's exponent and three comparisons of its mantissa
    # (no logarithm per pixel): depth / start = m 2^e with m in [0.5, 1)
    if depth <= start:
        return 0
    m, e = math.frexp(depth / start)
    m *= 2.0
    b = 4 * (e - 1) + (m >= _Q1) + (m >= _Q2) + (m >= _Q3)
    return min(bands - 1, b)


def band_of(depth: float) -> int:
    """The band of a depth in metres (depths under `BAND_START` fall in band 0, beyond the last in the last).

    Example:
        >>> band_of(0.05), band_of(0.1), band_of(0.11), band_of(1000.0)
        (0, 4, 4, 39)
    """
    return _band(float(depth), BAND_START, BANDS)


def band_edge(band: int) -> float:
    """The lower edge of a band, metres (`band_edge(b + 1)` is its upper edge)."""
    return BAND_START * 2.0 ** (band / 4)


@numba.njit(cache=True)
def _compare_kernel(depth, fx, fy, cx, cy, to_previous, previous, pfx, pfy, pcx, pcy, stride,
                    start, agree_m, agree_rel, near, sampled, compared, agreed):
    H, W = depth.shape
    h, w = previous.shape
    n = sampled.shape[0]
    for v in range(0, H, stride):
        for u in range(0, W, stride):
            z = depth[v, u]
            if not (z > 0 and z >= near):
                continue
            b = _band(z, start, n)
            sampled[b] += 1
            x = (u - cx) / fx * z
            y = (v - cy) / fy * z
            px = to_previous[0, 0] * x + to_previous[0, 1] * y + to_previous[0, 2] * z + to_previous[0, 3]
            py = to_previous[1, 0] * x + to_previous[1, 1] * y + to_previous[1, 2] * z + to_previous[1, 3]
            pz = to_previous[2, 0] * x + to_previous[2, 1] * y + to_previous[2, 2] * z + to_previous[2, 3]
            if not pz > 0:
                continue
            pu = int(math.floor(pfx * px / pz + pcx + 0.5))
            pv = int(math.floor(pfy * py / pz + pcy + 0.5))
            if pu < 0 or pu >= w or pv < 0 or pv >= h:
                continue
            d = previous[pv, pu]
            if not (d > 0 and d >= near):
                continue
            compared[b] += 1
            if abs(d - pz) <= max(agree_m, agree_rel * pz):
                agreed[b] += 1


def compare_depth(
    frame: Frame,  # with depth
    previous: Frame,  # with depth
    stride: int = STRIDE,
    near: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # sampled [BANDS], compared [BANDS], agreed [BANDS] int64
    """Per band of ``frame``'s depth: its sampled valid pixels, those that land on measured depth of
    ``previous``, and those that agree with it (module docstring); depth under ``near`` counts as
    missing in both (a session's `range.near`: depth it ignores already)."""
    if frame.depth is None or previous.depth is None:
        raise ValueError("depth: comparing frames needs depth in both")
    return _compare(frame.depth.numpy(), frame.camera, previous.depth.numpy(), previous.camera, stride, near)


def _compare(depth: np.ndarray, cam: Camera, previous: np.ndarray, prev: Camera, stride: int = STRIDE,
             near: float = 0.0):
    to_previous = np.linalg.inv(prev.c2w64()) @ cam.c2w64()
    counts = [np.zeros(BANDS, np.int64) for _ in range(3)]
    _compare_kernel(depth, cam.fx, cam.fy, cam.cx, cam.cy, np.ascontiguousarray(to_previous[:3]), previous,
                    prev.fx, prev.fy, prev.cx, prev.cy, stride, BAND_START, AGREE_M, AGREE_REL, float(near), *counts)
    return counts[0], counts[1], counts[2]


def inconsistent_below(compared: np.ndarray, agreed: np.ndarray) -> int | None:
    """The highest band whose frames disagree (at least `MIN_COMPARED` comparisons, under `DISAGREES`
    agreeing) when at least one band beyond it has enough comparisons and every such band agrees (at
    least `AGREES`); None otherwise. Depth up to that band's upper edge is not of the scene.

    Example:
        >>> compared = np.zeros(BANDS, np.int64); agreed = np.zeros(BANDS, np.int64)
        >>> compared[[5, 12]] = 1000; agreed[[5, 12]] = [20, 950]
        >>> inconsistent_below(compared, agreed), round(band_edge(6), 3)
        (5, 0.141)
    """
    measured = compared >= MIN_COMPARED
    share = np.where(measured, agreed / np.maximum(compared, 1), np.nan)
    bad = np.flatnonzero(measured & (share < DISAGREES))
    if bad.size == 0:
        return None
    top = int(bad[-1])
    beyond = share[top + 1:][measured[top + 1:]]
    if beyond.size == 0 or not (beyond >= AGREES).all():
        return None
    return top


class DepthConsistency:
    """The running comparison of a stream's consecutive frames with depth (module docstring): counts
    over every pair this object saw, and a warning for each frame with depth in bands that disagree."""

    def __init__(self):
        self.compared = np.zeros(BANDS, np.int64)
        self.agreed = np.zeros(BANDS, np.int64)
        self._previous: tuple[np.ndarray, Camera] | None = None  # the last frame's depth and camera, nothing more

    def limit(self) -> float | None:
        """Metres: the depth under which this stream's consecutive frames disagree, or None while they
        agree or too few were compared: the lower edge of the first band beyond `inconsistent_below`'s
        that was compared enough (they all agree), so that the bands between, too thinly sampled to
        tell, count with the disagreeing ones (a near limit set at the disagreeing band's upper edge
        would keep their depth, as unreliable as the bands under it)."""
        top = inconsistent_below(self.compared, self.agreed)
        return None if top is None else self._advised(self._agreeing_from(top))

    def _agreeing_from(self, top: int) -> int:
        beyond = np.flatnonzero(self.compared[top + 1:] >= MIN_COMPARED)  # not empty: `inconsistent_below`
        return top + 1 + int(beyond[0])

    @staticmethod
    def _advised(band: int) -> float:
        """The lower edge of ``band`` rounded up to the centimetre: a near limit set to the figure
        shown (two decimals) then leaves no depth of the bands under it."""
        return math.ceil(round(band_edge(band) * 100, 6)) / 100

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The counts, for a snapshot (the previous frame is not kept: a restored stream compares its
        next frame with none)."""
        return {"compared": self.compared.copy(), "agreed": self.agreed.copy()}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "DepthConsistency":
        """`to_arrays`' counts back (none: a fresh tracker, as for a snapshot written before they were
        kept); raises ValueError for counts of another shape or that do not add up."""
        tracker = cls()
        if not arrays:
            return tracker
        compared, agreed = (np.asarray(arrays.get(k, ())) for k in ("compared", "agreed"))
        if (compared.shape != (BANDS,) or agreed.shape != (BANDS,) or not np.issubdtype(compared.dtype, np.integer)
                or not np.issubdtype(agreed.dtype, np.integer) or not ((0 <= agreed) & (agreed <= compared)).all()):
            raise ValueError(f"consistency: expected integer counts [{BANDS}] with 0 <= agreed <= compared, got "
                             f"compared {compared.dtype} {list(compared.shape)}, agreed {agreed.dtype} {list(agreed.shape)}")
        tracker.compared[:], tracker.agreed[:] = compared, agreed
        return tracker

    def forget_previous(self) -> None:
        """Compare the next frame with none (the last one was rolled back); the counts stay."""
        self._previous = None

    def observe(self, frame: Frame, near: float = 0.0) -> list[str]:
        """Compare ``frame`` (with depth) with the previous one and return the warnings for it; depth
        under ``near`` (the session's `range.near`, ignored already) is neither compared nor warned about."""
        if frame.depth is None:
            raise ValueError("depth: the consistency check needs a frame with depth")
        current = (frame.depth.numpy(), frame.camera)
        previous, self._previous = self._previous, current
        if previous is None:
            return []
        sampled, compared, agreed = _compare(*current, *previous, near=near)
        self.compared += compared
        self.agreed += agreed
        top = inconsistent_below(self.compared, self.agreed)
        if top is None or sampled.sum() == 0:
            return []
        first = self._agreeing_from(top)  # the first band known to agree: `limit`
        share = sampled[:first].sum() / sampled.sum()
        if share < WARN_SHARE:
            return []
        limit = self._advised(first)
        below = self.compared[:first].sum(), self.agreed[:first].sum()
        beyond = np.flatnonzero(self.compared[first:] >= MIN_COMPARED) + first
        agree = self.agreed[beyond].sum() / self.compared[beyond].sum()
        return [f"depth: {share:.0%} of this frame's depth lies under {limit:.2f} m, where this session's consecutive "
                f"frames disagree ({below[1]} of {below[0]} sampled pixels agree; {agree:.0%} from "
                f"{limit:.2f} m on): likely under the sensor's working range; the setting "
                f"range.near={limit:.2f} ignores it"]
