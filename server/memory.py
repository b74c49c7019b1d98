"""The service's memory: a budget that every fold reserves its worst case from before it runs, and the
return of a deleted or evicted session's memory to the system.

A frame of a few kilobytes can fold into a million voxels (a flat black image over a smooth depth ramp
at fine voxels), so the request's size says nothing of what it costs. What bounds it is the frame
itself: a fold adds at most one voxel per pixel it lifts, so `canonical_core.scene.folding.fold_cost`
prices a frame before it folds, and `MemoryBudget.reserve` refuses it (`MemoryBudgetExceeded`, a 413
naming the budget) when the sessions' memory plus the folds under way would pass the service's budget.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from canonical_core.scene import release_scratch

from .session_errors import MemoryBudgetExceeded


class MemoryBudget:
    """At most ``limit`` bytes for the sessions' scenes (``in_use``) and the folds under way together.

    Example:
        >>> budget = MemoryBudget(100, lambda: 60)
        >>> with budget.reserve(30):
        ...     budget.reserved
        30
        >>> budget.reserve(50).__enter__()
        Traceback (most recent call last):
        ...
        server.session_errors.MemoryBudgetExceeded: frame: folding it may take up to 50 bytes; the service's memory budget (CANONICAL_MEMORY_BUDGET_BYTES, 100 bytes) has 40 bytes left
    """

    def __init__(self, limit: int, in_use: Callable[[], int]):
        self.limit, self._in_use = limit, in_use
        self.reserved = 0
        self._lock = threading.Lock()

    @contextmanager
    def reserve(self, nbytes: int) -> Iterator[None]:
        """Hold ``nbytes`` of the budget while the block runs (a fold), or raise before it runs."""
        with self._lock:
            left = self.limit - self._in_use() - self.reserved
            if nbytes > left:
                raise MemoryBudgetExceeded(
                    f"frame: folding it may take up to {_size(nbytes)}; the service's memory budget "
                    f"(CANONICAL_MEMORY_BUDGET_BYTES, {_size(self.limit)}) has {_size(max(left, 0))} left")
            self.reserved += nbytes
        try:
            yield
        finally:
            with self._lock:
                self.reserved -= nbytes


def _size(nbytes: int) -> str:
    return f"{nbytes / 2**20:.0f} MiB" if nbytes >= 2**20 else f"{nbytes} bytes"


def release_memory() -> None:
    """Return what dropped sessions held: collect the cycles that keep a session alive (it and its
    snapshots and corrections refer to each other), drop the folds' spare work arrays (sized for the
    largest frame folded so far; the next fold makes its own), then ask glibc to give its freed heap
    back (it keeps it for reuse otherwise, so the process's resident memory never falls)."""
    gc.collect()
    release_scratch()
    trim_heap()


def trim_heap() -> None:
    """Ask glibc to give the heap's free pages back to the system (a no-op elsewhere)."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _libc():
    name = ctypes.util.find_library("c")
    try:
        lib = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return lib if lib is not None and hasattr(lib, "malloc_trim") else None


_LIBC = _libc()
