"""Which frames are inputs and which are held out (positions 0..n-1 in the sequence).

The rules, for a sequence of n frames and a list of input counts ``views``:

- Inputs for N views: ``round(linspace(0, n - 1, N))``, evenly spread over the whole sequence.
- Held-out frames: for each target in ``linspace(2, n - 3, 10)``, the nearest position that is
  *unused*, ties to the lower position. Unused means: not an input for any N in ``views`` (the
  union of all input sets) and not already held out. So one fixed set of held-out frames serves
  every N, and no held-out frame is ever an input.
- Extrapolation ("target span 20 % larger than the input span"): the same held-out frames; the
  inputs are spread over the central part of the sequence, ``linspace(lo, hi, N)`` with
  ``hi - lo = (max(heldout) - min(heldout)) / 1.2`` centred on the held-out span, each target
  snapped to the nearest position that is neither held out nor already taken (same tie rule).
  The sequence allows it when every snapped input stays inside ``[floor(lo), ceil(hi)]``.
- Feature stability uses N = 2..12 inputs: the evenly spread positions snapped the same way
  around the held-out frames (for the N in ``views`` nothing moves).

Example:
    >>> split = interpolation_split(50, [2, 4, 8, 16])
    >>> split.heldout
    (2, 6, 12, 17, 22, 27, 32, 37, 41, 47)
    >>> split.inputs[4]
    (0, 16, 33, 49)
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

HELDOUT_COUNT = 10
EXTRAPOLATION_RATIO = 1.2  # target span / input span
STABILITY_VIEWS = tuple(range(2, 13))  # N = 2..12; the largest is the reference splat


@dataclass(frozen=True)
class Split:
    """Held-out positions and, per input count N, the input positions (all sorted, 0-based)."""

    heldout: tuple[int, ...]
    inputs: dict[int, tuple[int, ...]]

    def span_ratio(self, views: int) -> float:
        """(held-out span) / (input span) for N = ``views``."""
        inputs = self.inputs[views]
        return (max(self.heldout) - min(self.heldout)) / max(inputs[-1] - inputs[0], 1)


def _check_views(n: int, views: Sequence[int]) -> list[int]:
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n: expected a positive number of frames, got {n!r}")
    if not views or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in views):
        raise ValueError(f"views: expected a non-empty list of positive integers, got {list(views)!r}")
    if max(views) > n:
        raise ValueError(f"views: {max(views)} input views requested, but the sequence has only {n} frames")
    return sorted(set(views))


def spread(n: int, count: int) -> tuple[int, ...]:
    """``round(linspace(0, n - 1, count))``: distinct when count <= n (steps are >= 1)."""
    return tuple(int(p) for p in np.round(np.linspace(0, n - 1, count)))


def nearest_free(targets: Iterable[float], taken: Iterable[int], n: int) -> tuple[int, ...]:
    """For each target in order, the nearest position in [0, n) that is neither in ``taken`` nor
    chosen for an earlier target; ties go to the lower position. Returned in target order."""
    used = set(taken)
    chosen = []
    for t in targets:
        free = [p for p in range(n) if p not in used]
        if not free:
            raise ValueError(f"n: no unused frame left among {n} for target position {t:g}")
        best = min(free, key=lambda p: (abs(p - t), p))
        used.add(best)
        chosen.append(best)
    return tuple(chosen)


def interpolation_split(n: int, views: Sequence[int], heldout_count: int = HELDOUT_COUNT) -> Split:
    """The main protocol (module docstring). Raises ValueError when n cannot hold the inputs and
    ``heldout_count`` unused frames, or is too short for the target range [2, n - 3]."""
    views = _check_views(n, views)
    if n < 6:
        raise ValueError(f"n: the held-out targets linspace(2, n - 3, ...) need at least 6 frames, got {n}")
    inputs = {v: spread(n, v) for v in views}
    union = set().union(*inputs.values())
    if n - len(union) < heldout_count:
        raise ValueError(
            f"views: the inputs for {views} use {len(union)} of {n} frames, leaving fewer than {heldout_count} to hold out"
        )
    heldout = nearest_free(np.linspace(2, n - 3, heldout_count), union, n)
    return Split(heldout=tuple(sorted(heldout)), inputs=inputs)


def extrapolation_split(n: int, views: Sequence[int], heldout: Sequence[int], ratio: float = EXTRAPOLATION_RATIO) -> Split | None:
    """Inputs over the central part so that the held-out span is ``ratio`` x the input span, or
    None when the sequence does not allow it (too few free frames in the central part)."""
    views = _check_views(n, views)
    if not ratio > 1:
        raise ValueError(f"ratio: expected a number above 1, got {ratio!r}")
    first, last = min(heldout), max(heldout)
    half = (last - first) / ratio / 2
    lo, hi = (first + last) / 2 - half, (first + last) / 2 + half
    inputs = {}
    for v in views:
        try:
            chosen = nearest_free(np.linspace(lo, hi, v), heldout, n)
        except ValueError:
            return None
        if min(chosen) < math.floor(lo) or max(chosen) > math.ceil(hi):
            return None
        inputs[v] = tuple(sorted(chosen))
    return Split(heldout=tuple(sorted(heldout)), inputs=inputs)


def stability_inputs(n: int, heldout: Sequence[int], views: Sequence[int] | None = None) -> dict[int, tuple[int, ...]]:
    """Input positions for the feature-stability curve: evenly spread, snapped around the held-out
    frames. ``views`` None: the counts of `STABILITY_VIEWS` that fit in the n - len(heldout) free
    frames; counts given must all fit (ValueError naming the ones that do not)."""
    free = n - len(set(heldout))
    if views is None:
        views = [v for v in STABILITY_VIEWS if v <= free]
    elif misfits := sorted({v for v in views if not 1 <= v <= free}):
        raise ValueError(f"stability_views: {misfits} do not fit: each count must be between 1 and the {free} frames "
                         f"that are not held out")
    return {v: tuple(sorted(nearest_free(spread(n, v), heldout, n))) for v in sorted(set(views))}
