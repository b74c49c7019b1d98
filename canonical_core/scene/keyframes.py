"""The views a scene keeps for the colour solve (`SceneConfig.colour_solve.views`).

`decode.solve_colours` fits the decoded colours to input views, so a streaming scene keeps some:
colour and camera only, resized by ``scale`` (half size fits nearly as well as full size at a
quarter of the solve's time and memory: `SceneConfig.colour_solve.scale`), at most ``capacity``,
spread evenly over the stream. When one too many
arrive, the interior keyframe whose neighbours are closest in stream order goes (the first and
the newest always stay), so the kept frames approach an even spacing as the stream grows, as
the evaluation's inputs are (`linspace` over frame positions).

Example:
    >>> import numpy as np, torch
    >>> from canonical_core.camera import Camera
    >>> camera = Camera(K=[[20, 0, 8], [0, 20, 6], [0, 0, 1]], c2w=np.eye(4), width=16, height=12)
    >>> keyframes = Keyframes(capacity=3, scale=0.5)
    >>> for index in range(6):
    ...     keyframes.add(index, Frame(rgb=np.zeros((12, 16, 3), np.uint8), camera=camera))
    >>> keyframes.indices, keyframes.frames()[0].rgb.shape
    ([0, 2, 5], torch.Size([6, 8, 3]))
"""

from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..frame import Frame, resize_frame


def view_to_arrays(prefix: str, frame: Frame) -> dict[str, np.ndarray]:
    """A frame's colour, camera and id as snapshot arrays named ``prefix.rgb``, ``.K``, ``.c2w``, ``.id``."""
    return {f"{prefix}.rgb": frame.rgb.numpy(), f"{prefix}.K": frame.camera.K64(), f"{prefix}.c2w": frame.camera.c2w64(),
            f"{prefix}.id": np.frombuffer((frame.frame_id or "").encode(), np.uint8)}


def view_from_arrays(prefix: str, arrays, **extra) -> Frame:
    """The inverse of `view_to_arrays`; ``extra`` fields (features, labels) go to the Frame."""
    rgb = arrays[f"{prefix}.rgb"]
    camera = Camera(arrays[f"{prefix}.K"], arrays[f"{prefix}.c2w"], rgb.shape[1], rgb.shape[0])
    return Frame(rgb=rgb.copy(), camera=camera, frame_id=arrays[f"{prefix}.id"].tobytes().decode() or None, **extra)


FILL_LEVELS = 2  # a line of the image that spans at most this many levels in each channel is one colour
MAX_FILL_SHARE = 0.25  # of each side: more is no border but the picture of something


def fill_margins(frame: Frame) -> tuple[int, int, int, int]:
    """Rows and columns at the image's edges (top, bottom, left, right) of one colour and without valid
    depth: the fill a colour image warped onto the depth camera gets at its edges (Kinect-style
    registration pads it with white or black). The fold never fuses them (they have no depth), but a
    colour solve that fitted them would paint each kept view's outline into the scene. At most
    `MAX_FILL_SHARE` of each side; none where a line holds valid depth, nor in a frame without depth.

    Example:
        >>> camera = Camera(K=[[20, 0, 8], [0, 20, 6], [0, 0, 1]], c2w=np.eye(4), width=16, height=12)
        >>> rgb = np.full((12, 16, 3), 255, np.uint8); rgb[2:, 1:14] = np.arange(13)[None, :, None] * 9
        >>> depth = np.zeros((12, 16), np.float32); depth[5:, 4:13] = 1.0
        >>> fill_margins(Frame(rgb=rgb, camera=camera, depth=depth))
        (2, 0, 1, 2)
    """
    if frame.depth is None:
        return 0, 0, 0, 0
    rgb, depth = frame.rgb.numpy(), frame.depth.numpy()

    def run(lines: np.ndarray, depths: np.ndarray) -> int:  # lines: [n, length, 3], from the edge in
        n = 0
        while n < int(len(lines) * MAX_FILL_SHARE) and np.ptp(lines[n], axis=0).max() <= FILL_LEVELS \
                and not (depths[n] > 0).any():
            n += 1
        return n

    rows, cols = (rgb, depth), (rgb.transpose(1, 0, 2), depth.T)
    return run(*rows), run(*(a[::-1] for a in rows)), run(*cols), run(*(a[::-1] for a in cols))


def kept_view(frame: Frame, scale: float) -> Frame:
    """What a scene keeps of ``frame`` for the colour solve: its colour and camera, without the fill at
    its edges (`fill_margins`: the view cropped, its principal point moved with it), resized by ``scale``."""
    top, bottom, left, right = fill_margins(frame)
    rgb, camera = frame.rgb, frame.camera
    width, height = camera.width - left - right, camera.height - top - bottom
    K = camera.K64()
    K[:2, 2] -= (left, top)
    if (top or bottom or left or right) and 0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height:  # a camera's K
        rgb, camera = rgb[top:top + height, left:left + width].contiguous(), Camera(K, camera.c2w64(), width, height)
    return resize_frame(Frame(rgb=rgb, camera=camera, frame_id=frame.frame_id), scale)


class Keyframes:
    def __init__(self, capacity: int, scale: float = 1.0):
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 0:
            raise ValueError(f"capacity: expected a non-negative integer, got {capacity!r}")
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 < scale <= 1:
            raise ValueError(f"scale: expected a number in (0, 1], got {scale!r}")
        self.capacity, self.scale = capacity, scale
        self.indices: list[int] = []  # stream positions of the kept frames, ascending
        self._frames: list[Frame] = []

    def __len__(self) -> int:
        return len(self._frames)

    def frames(self) -> list[Frame]:
        return list(self._frames)

    def add(self, index: int, frame: Frame, view: Frame | None = None) -> None:
        """Keep ``frame``'s colour and camera (stream position ``index``), evicting one if full;
        ``view``: its `kept_view` at this scale, made already."""
        if self.capacity == 0:
            return
        self.indices.append(index)
        self._frames.append(view if view is not None else kept_view(frame, self.scale))
        if len(self._frames) > self.capacity:
            if len(self._frames) <= 2:  # capacity 1: the newest view
                drop = 0
            else:  # the interior frame whose neighbours are closest: the densest part of the stream
                gaps = [self.indices[i + 1] - self.indices[i - 1] for i in range(1, len(self.indices) - 1)]
                drop = 1 + int(np.argmin(gaps))
            del self.indices[drop], self._frames[drop]

    def nbytes(self) -> int:
        return sum(f.rgb.numel() for f in self._frames)

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"indices": np.asarray(self.indices, np.int64)}
        for i, f in enumerate(self._frames):
            arrays |= view_to_arrays(str(i), f)
        return arrays

    @classmethod
    def from_arrays(cls, capacity: int, scale: float, arrays: dict[str, np.ndarray]) -> "Keyframes":
        """The inverse of `to_arrays` (no arrays: none kept, as in snapshots from before keyframes)."""
        keyframes = cls(capacity, scale)
        for i, index in enumerate(arrays.get("indices", np.zeros(0, np.int64)).tolist()):
            keyframes.indices.append(int(index))
            keyframes._frames.append(view_from_arrays(str(i), arrays))
        return keyframes
