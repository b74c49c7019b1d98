"""`FrameSequence`: a lazily-loading, sliceable sequence of `Frame`s.

A loader resolves a capture into sources (a frame id and a way to read it) up front, so missing
files and malformed poses fail at load time; images are read only when a frame is indexed.
Listing a capture needs numpy alone: the loaders check intrinsics and poses with `calibration`
and import `Camera` and `Frame` (and with them torch) only when a frame is read, and numba's depth
conversion (`depth_codes`) loads with its first use, so a client that sends a capture's files as
they are (`canonical stream`) starts without loading either.

Example:
    >>> from canonical_core.datasets import synthetic_rgbd
    >>> seq = synthetic_rgbd(num_frames=4, width=64, height=48)
    >>> len(seq), seq.frame_ids[:2], len(seq[1:3]), seq[-1].frame_id
    (4, ['000000', '000001'], 2, '000003')
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol, overload

import numpy as np

if TYPE_CHECKING:
    from ..frame import Frame


class FrameSource(Protocol):
    """Anything with a ``frame_id``, a ``load()`` that returns the `Frame`, and a ``view()`` that
    returns its camera without reading the frame: (K [3, 3], c2w [4, 4], float64, width, height),
    the image size from the colour file's header and the intrinsics checked against it, no pixel
    decoded and no torch loaded (a client that asks for a render at a capture's frame)."""

    frame_id: str

    def load(self) -> Frame: ...

    def view(self) -> tuple[np.ndarray, np.ndarray, int, int]: ...


class FrameSequence(Sequence["Frame"]):
    """Frames of one capture, read on access.

    Args:
        name: a human-readable name (usually the capture's folder name).
        sources: one `FrameSource` per frame, in order.

    ``seq[i]`` (negative too) reads and returns frame i; ``seq[a:b:c]`` returns a FrameSequence
    without reading anything; ``seq.frame_ids`` lists ids without reading images.
    """

    def __init__(self, name: str, sources: Sequence[FrameSource]):
        if not isinstance(name, str):
            raise ValueError(f"name: expected a string, got {type(name).__name__}")
        self.name = name
        self._sources = tuple(sources)

    @property
    def frame_ids(self) -> list[str]:
        return [s.frame_id for s in self._sources]

    def source(self, index: int) -> FrameSource:
        """Where frame ``index`` is read from, without reading it (a client may send a capture's files
        as they are rather than decode them)."""
        return self._sources[operator.index(index)]

    def __len__(self) -> int:
        return len(self._sources)

    @overload
    def __getitem__(self, index: int) -> Frame: ...

    @overload
    def __getitem__(self, index: slice) -> "FrameSequence": ...

    def __getitem__(self, index):
        if isinstance(index, slice):
            return FrameSequence(self.name, self._sources[index])
        i = operator.index(index)  # TypeError for non-integers, as list does
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame index {i} out of range for {len(self)} frames")
        return self._sources[i].load()

    def __repr__(self) -> str:
        ids = self.frame_ids
        shown = ids if len(ids) <= 4 else ids[:2] + ["..."] + ids[-1:]
        return f"FrameSequence({self.name!r}, {len(self)} frames, ids={shown})"
