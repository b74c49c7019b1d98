"""A session's frame-id table: for each ``frame_id`` it folded, where and what (`FoldedFrame`), so that
a retry after a lost answer is recognised and answered instead of folded again.

A stream at 30 frames a second names over a hundred thousand frames an hour, and the table is
written whole into the frame log's checkpoint at every snapshot, under the session's lock. So it
keeps the whole fold report of its `REPORTS_KEPT` latest frames only (a retry comes seconds after
its frame, not thousands of frames later); an older frame's retry is still recognised by its digest
and answered with its index and zero counts, as a frame whose report a crash lost is.
"""

from __future__ import annotations

import collections
import dataclasses

REPORTS_KEPT = 1024


@dataclasses.dataclass(frozen=True)
class FoldedFrame:
    """What the session remembers of a frame that carried a frame_id: enough to answer its retry."""

    index: int
    digest: str  # of its log record's payload
    report: dict | None  # its fold's; None where a crash left only its record (a retry gets zero counts)


class FrameIds(dict):
    """``frame_id`` -> `FoldedFrame`, holding the reports of the `REPORTS_KEPT` latest.

    Example:
        >>> ids = FrameIds({f"f{k}": FoldedFrame(k, "d", {"frame_index": k}) for k in range(REPORTS_KEPT + 2)})
        >>> ids["f0"].report, ids["f2"].report
        (None, {'frame_index': 2})
    """

    def __init__(self, entries=()):
        super().__init__(entries)
        reported = sorted((k for k, v in self.items() if v.report is not None), key=lambda k: self[k].index)
        self._reported = collections.deque(reported)  # keys whose entries hold a report, oldest first
        self._forget_old()

    def __setitem__(self, key, value) -> None:
        super().__setitem__(key, value)
        if value.report is not None:
            self._reported.append(key)
            self._forget_old()

    def _forget_old(self) -> None:
        while len(self._reported) > REPORTS_KEPT:
            key = self._reported.popleft()
            known = self.get(key)
            if known is not None and known.report is not None:
                super().__setitem__(key, dataclasses.replace(known, report=None))
