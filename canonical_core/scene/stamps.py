"""Change stamps: what tells the decoder side which voxels' sums changed since it decoded them.

A map stamps the voxels each change writes (`VoxelMap.changed_at`, int32), and the decoded rows keep
the stamp of the sums they came from (`decoded.DecodedRows`): equal stamps of one epoch mean equal
sums, so a decode after a fold redoes only what the fold changed.
"""

from __future__ import annotations

import threading

STAMP_LIMIT = 2**31 - 1  # change stamps are int32 (`voxel_map.VoxelMap.changed_at`, `decoded.DecodedRows.stamps`)


class StampClock:
    """Change stamps, unique in the process within an epoch (so that inputs of one map can never
    match another map's decoded rows): 1, 2, ... up to ``limit``, then a new epoch from 1 again.

    A stamp of a new epoch may equal one an earlier epoch gave, so what compares stamps compares
    epochs first: a map restamps every voxel when it first stamps in a new epoch
    (`voxel_map.VoxelMap.stamp_epoch`), and decoded rows of another epoch are all stale (`decoding.SceneDecoding.take`).

    Example:
        >>> clock = StampClock(limit=2)
        >>> [clock.next() for _ in range(3)]
        [(0, 1), (0, 2), (1, 1)]
    """

    def __init__(self, limit: int = STAMP_LIMIT):
        self.limit = limit
        self.epoch, self.last = 0, 0  # the last stamp given, and its epoch
        self._lock = threading.Lock()  # scenes fold on several threads

    def next(self) -> tuple[int, int]:
        """A fresh (epoch, stamp)."""
        with self._lock:
            if self.last >= self.limit:
                self.epoch, self.last = self.epoch + 1, 0
            self.last += 1
            return self.epoch, self.last


STAMPS = StampClock()  # the process's
