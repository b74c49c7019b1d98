"""The per-session lease that keeps one writer per session folder when several processes serve one
data directory (a volume every node mounts)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import struct
import threading
from pathlib import Path

from ..framelog import Fenced
from ..session_errors import TooManySessions
from ..store import TOMBSTONE

EPOCH = "owner.epoch"
CREATING = "creating.lock"  # in the data directory: the owners create sessions one at a time


def sessions_on_disk(data_dir: Path) -> int:
    """The sessions a data directory holds (deleted ones, still being removed, not counted)."""
    root = Path(data_dir) / "sessions"
    if not root.is_dir():
        return 0
    return sum(1 for p in root.iterdir() if p.is_dir() and not p.name.startswith(TOMBSTONE))


@contextlib.contextmanager
def one_creator(data_dir: Path, max_sessions: int):
    """Held while an owner creates a session: the owners of a data directory take turns (an exclusive
    flock of its `CREATING` file), so that each counts the sessions the others made and, together,
    they never pass ``max_sessions`` (`TooManySessions`, 409)."""
    fd = os.open(Path(data_dir) / CREATING, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        held = sessions_on_disk(data_dir)
        if held >= max_sessions:
            raise TooManySessions(f"max_sessions: the service holds {held} sessions, its limit")
        yield
    finally:
        os.close(fd)  # and with it the lock


class Lease:
    """The right to write one session folder, held by one owner at a time (several processes may
    serve the folder's data directory, e.g. on a shared volume).

    The folder's ``owner.epoch`` holds a number (u64). A new owner increments it (`take`) before it
    reads the folder; every write checks that the number is still its own (`held`). Both happen under
    an exclusive ``flock`` of that file, so a check and the write it guards are one step for any other
    owner: an owner presumed dead that is still running (a partition, a long pause) gets `Fenced` on
    its next write instead of writing after its successor read the folder. Re-entrant within a process.
    """

    def __init__(self, folder: Path):
        self.path = folder / EPOCH
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        self.epoch: int | None = None  # this owner's epoch, once taken
        self._mutex = threading.RLock()
        self._depth = 0

    @contextlib.contextmanager
    def _locked(self):
        with self._mutex:
            if self._depth == 0:
                fcntl.flock(self._fd, fcntl.LOCK_EX)
            self._depth += 1
            try:
                yield
            finally:
                self._depth -= 1
                if self._depth == 0:
                    fcntl.flock(self._fd, fcntl.LOCK_UN)

    def current(self) -> int:
        """The epoch on disk (0 before any owner took the folder)."""
        data = os.pread(self._fd, 8, 0)
        return struct.unpack("<Q", data)[0] if len(data) == 8 else 0

    @contextlib.contextmanager
    def take(self):
        """Become the owner (epoch + 1, fsynced); the lock stays held inside the block, where the new
        owner reads the folder, so no write of the previous owner lands after that read."""
        with self._locked():
            epoch = self.current() + 1
            os.pwrite(self._fd, struct.pack("<Q", epoch), 0)
            os.fsync(self._fd)
            self.epoch = epoch
            yield epoch

    @contextlib.contextmanager
    def held(self):
        """Run a write as the owner: `Fenced` (before anything is written) if the epoch is not ours."""
        with self._locked():
            now = self.current()
            if now != self.epoch:
                raise Fenced(f"{self.path.parent.name}: another owner took the session (epoch {now}; this "
                             f"process held {self.epoch}); nothing was written")
            yield

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
