"""The service's memory: a budget that every fold reserves its worst case from before it runs, and the
return of a deleted or evicted session's memory to the system.

A frame of a few kilobytes can fold into a million voxels (a flat black image over a smooth depth ramp
at fine voxels), so the request's size says nothing of what it costs. What bounds it is the frame
itself: a fold adds at most one voxel per pixel it lifts, so `canonical_core.scene.folding.fold_cost`
prices a frame before it folds, and `MemoryBudget.reserve` refuses it when the sessions' memory plus the
folds under way would pass the service's budget. A frame's decoded arrays are held from the budget too,
from their decode until the frame is answered: a compressed body of kilobytes can decode to hundreds of
megabytes, and numbered frames wait decoded for their turn.

A frame that cannot fit beside what the sessions hold is refused for good (`MemoryBudgetExceeded`, 413);
one that fits beside them but not beside the folds and frames under way now waits for nothing and is
answered 429 (`MemoryBudgetBusy`): those give their share back within moments, and a client sends it again.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import threading
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from canonical_core.scene import release_scratch

from .session_errors import MemoryBudgetBusy, MemoryBudgetExceeded


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
        self.reserved = 0  # by the folds under way
        self.decoded = 0  # by decoded frames waiting for their turn or their fold
        self._lock = threading.Lock()

    @property
    def held(self) -> int:
        """What the folds under way and the decoded frames hold now."""
        return self.reserved + self.decoded

    @contextmanager
    def reserve(self, nbytes: int) -> Iterator[None]:
        """Hold ``nbytes`` of the budget while the block runs (a fold), or raise before it runs."""
        self.take(nbytes)
        try:
            yield
        finally:
            self.give(nbytes)

    def take(self, nbytes: int, use: str = "folding it may take", decoded: bool = False) -> None:
        """Hold ``nbytes`` until `give`; `MemoryBudgetExceeded` if they do not fit beside the sessions'
        memory, `MemoryBudgetBusy` if they do but not beside what is held now. A fold (``decoded``
        false) is weighed against the folds under way only, never against the ``decoded`` frames
        waiting: those wait for it (the numbered frames after it, and its own arrays), and a fold
        refused for them would never be taken. The decoded frames give way to the folds instead."""
        with self._lock:
            free = self.limit - self._in_use()
            held = self.held if decoded else self.reserved
            if nbytes > free - held:
                message = (f"frame: {use} up to {_size(nbytes)}; the service's memory budget (CANONICAL_MEMORY_BUDGET_BYTES, "
                           f"{_size(self.limit)}) has {_size(max(free - held, 0))} left")
                if nbytes > free:
                    raise MemoryBudgetExceeded(message)
                raise MemoryBudgetBusy(f"{message}, beside {_size(held)} that folds and decoded frames hold "
                                       "for moments; send it again")
            if decoded:
                self.decoded += nbytes
            else:
                self.reserved += nbytes

    def give(self, nbytes: int, decoded: bool = False) -> None:
        with self._lock:
            if decoded:
                self.decoded -= nbytes
            else:
                self.reserved -= nbytes


class DecodedHold:
    """``frame``'s decoded bytes held from ``budget`` (nothing without one) until `release` (once;
    later calls do nothing), or until the hold is dropped unreleased (a request cancelled while its
    frame was decoded in a worker: the result never reached the route). Raises as `MemoryBudget.take`."""

    def __init__(self, budget: MemoryBudget | None, frame):
        self._give = lambda: None
        if budget is not None:
            nbytes = frame_bytes(frame)
            budget.take(nbytes, "holding its decoded arrays takes", decoded=True)
            self._give = weakref.finalize(self, budget.give, nbytes, True)

    def release(self) -> None:
        self._give()


def frame_bytes(frame) -> int:
    """Bytes of a decoded frame's arrays (what it holds while it waits for its turn and folds)."""
    tensors = (frame.rgb, frame.depth, frame.depth_std, frame.features, frame.labels)
    return sum(t.numel() * t.element_size() for t in tensors if t is not None)


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
