"""A posed camera frame: the unit that is folded into a scene.

Example:
    >>> import numpy as np, torch
    >>> cam = Camera(K=[[500, 0, 32], [0, 500, 24], [0, 0, 1]], c2w=np.eye(4), width=64, height=48)
    >>> f = Frame(rgb=np.zeros((48, 64, 3), np.uint8), camera=cam, depth=np.ones((48, 64), np.float32))
    >>> f.rgb.shape, f.has_depth
    (torch.Size([48, 64, 3]), True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from PIL import Image
from torch import Tensor

from .calibration import validate_image_intrinsics
from .camera import Camera
from .resample import area_resize, depth_size_problem

MAX_IMAGE_PIXELS = 4096 * 4096
# Frames without depth get it from a plane sweep and wait, whole, in the source window and the
# pending list (and so in every snapshot) until a partner view arrives: they cost far more per
# pixel than frames with depth, so their size has a lower bound.
MAX_RGB_ONLY_PIXELS = 2048 * 2048
# Client features and label scores are sampled at every valid image pixel (pixels x channels
# values per frame), and label scores add one float per channel to every voxel of the scene.
MAX_FEATURE_CHANNELS = 512
MAX_LABEL_CHANNELS = 256
# A scene stores its feature and label-score means in float16 (`scene.stored`), which ends at this
# value: a larger mean would be stored as inf, and would poison its voxel for good. A mean stays within
# the range of what it averages, so values up to this are safe. Client features may be projected to
# the session's feature channels (orthonormally), which mixes a pixel's channels: each projected
# channel is then bounded by the norm of the pixel's feature vector, not by its largest value.
MAX_STORED_VALUE = float(np.finfo(np.float16).max)
MIN_RGB_ONLY_SIDE = 8  # the plane sweep matches at half resolution and needs a few pixels a side
# A frame's id is kept in memory, in the log and in every snapshot: a name, not a payload.
MAX_FRAME_ID_BYTES = 256


def _tensor(value, field: str) -> Tensor:
    if isinstance(value, Tensor):
        return value.detach().cpu()
    if isinstance(value, np.ndarray):
        # torch cannot wrap a read-only array (e.g. np.asarray of a PIL image) without warning that
        # writes would be undefined: such arrays are copied; writable ones are shared as before
        array = np.ascontiguousarray(value)
        return torch.from_numpy(array if array.flags.writeable else array.copy())
    raise ValueError(f"{field}: expected a numpy array or torch tensor, got {type(value).__name__}")


def _float_array(value, field: str, shape: tuple[int, int]) -> np.ndarray:
    """``value`` checked as a float map of ``shape`` (metres), as a numpy array: the caller's own
    memory where it can be (a wire frame's read-only buffer included), converted only from a tensor."""
    if isinstance(value, Tensor):
        if not value.is_floating_point():
            raise ValueError(f"{field}: expected a float array (metres), got dtype {value.dtype}")
        array = value.detach().cpu().to(torch.float32).numpy()
    elif isinstance(value, np.ndarray):
        if not np.issubdtype(value.dtype, np.floating):
            raise ValueError(f"{field}: expected a float array (metres), got dtype {value.dtype}")
        array = value
    else:
        raise ValueError(f"{field}: expected a numpy array or torch tensor, got {type(value).__name__}")
    if tuple(array.shape) != shape:
        raise ValueError(f"{field}: expected shape {list(shape)} to match the {'depth' if field == 'depth_std' else 'image'}, "
                         f"got {list(array.shape)}")
    return array


def _float_map(value, field: str, shape: tuple[int, int]) -> Tensor:
    """A float map that must be finite everywhere, as float32 [H, W] (a copy: the frame owns it)."""
    t = torch.from_numpy(np.array(_float_array(value, field, shape), dtype=np.float32))
    if not torch.isfinite(t).all():
        raise ValueError(f"{field}: contains NaN or inf")
    return t


@numba.njit(cache=True)
def _cleaned_depth(depth, out) -> bool:  # [H, W] float32 -> out; True if a value is negative
    """Missing depth (NaN, inf) as 0 in ``out``, in one pass; stops at the first negative value
    (-inf included), which is an error of the frame, not a missing measurement."""
    source, target = depth.ravel(), out.ravel()
    for i in range(source.shape[0]):
        v = source[i]
        if v < 0:
            return True
        target[i] = v if np.isfinite(v) else np.float32(0.0)
    return False


def _depth_map(value, shape: tuple[int, int]) -> Tensor:
    """``depth`` as float32 [H, W] metres with missing values as 0, checked and cleaned in one pass
    (it is on every fold's path: a wire frame's depth is read where it arrived, not copied first)."""
    cleaned = np.empty(shape, np.float32)
    if _cleaned_depth(np.ascontiguousarray(_float_array(value, "depth", shape), dtype=np.float32), cleaned):
        raise ValueError("depth: negative values (depth is metres along the optical axis; 0 = missing)")
    return torch.from_numpy(cleaned)


def _channel_map(value, field: str, max_channels: int, mixed: bool = False) -> Tensor:
    """A float map [H', W', C] as float32, its values within what a scene stores (`MAX_STORED_VALUE`);
    ``mixed``: its channels may be mixed (a projection), so each pixel's vector norm is bounded too."""
    t = _tensor(value, field)
    if t.ndim != 3 or min(t.shape) < 1:
        raise ValueError(f"{field}: expected shape [H', W', C], got {list(t.shape)}")
    if t.shape[-1] > max_channels:
        raise ValueError(f"{field}: {t.shape[-1]} channels exceed the limit of {max_channels}")
    if not t.is_floating_point():
        raise ValueError(f"{field}: expected a float array, got dtype {t.dtype}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{field}: contains NaN or inf")
    top = float(t.abs().max())  # before float32: a float64 value beyond float32 is named as it was given
    if top > MAX_STORED_VALUE:
        raise ValueError(f"{field}: largest magnitude {top:.6g} exceeds {MAX_STORED_VALUE:g}, the largest value "
                         "a scene stores (float16); scale the values down")
    t = t.to(torch.float32)
    if mixed and top * t.shape[-1] ** 0.5 > MAX_STORED_VALUE:  # else no pixel's norm can exceed it
        norm = float(torch.linalg.vector_norm(t, dim=-1).max())  # squares of values <= 65504 fit float32
        if norm > MAX_STORED_VALUE:
            raise ValueError(f"{field}: a pixel's feature vector has norm {norm:.6g}, above {MAX_STORED_VALUE:g}, "
                             "the largest value a scene stores (float16), which a projection of its channels "
                             "may reach; scale the values down")
    return t.contiguous()


def _class_map(t: Tensor, num_classes) -> Tensor:  # [H', W'] integer ids -> int16, -1 = none
    """A class map checked against ``num_classes``: ids 0..K-1, any negative id meaning no class."""
    if t.is_floating_point() or t.is_complex():
        raise ValueError(f"labels: a class map [H', W'] holds integer class ids, got dtype {t.dtype}")
    if min(t.shape) < 1:
        raise ValueError(f"labels: a class map must have at least one pixel, got shape {list(t.shape)}")
    if isinstance(num_classes, bool) or not isinstance(num_classes, (int, np.integer)):
        raise ValueError(f"num_classes: required with a class map (labels as integer [H', W']): the number of "
                         f"classes K, got {num_classes!r}")
    if not 1 <= num_classes <= MAX_LABEL_CHANNELS:
        raise ValueError(f"num_classes: expected 1..{MAX_LABEL_CHANNELS} classes, got {num_classes}")
    # numpy's max: torch has none for uint16/32/64 (16-bit label PNGs), and it keeps a uint64 above
    # int64's range exact (refused below as any id >= num_classes is)
    top = int(t.numpy().max())
    if top >= num_classes:
        raise ValueError(f"labels: class {top} does not fit num_classes = {num_classes} (ids 0..{num_classes - 1}; "
                         "negative: no class)")
    # every id is below num_classes now: any integer type converts to int64 exactly; clamped where -1 exists
    return t.to(torch.int64).clamp_min(-1).to(torch.int16).contiguous()


def _map_size(value) -> tuple[int, int] | None:
    """(rows, columns) of a 2-D array or tensor; None for anything else (its own check names it)."""
    shape = getattr(value, "shape", None)
    return (int(shape[0]), int(shape[1])) if shape is not None and len(shape) == 2 else None


def _colour_at_depth_size(
    rgb: Tensor,  # [H, W, 3] uint8
    camera: Camera,
    size: tuple[int, int],  # (h, w) of the depth map
) -> tuple[Tensor, Camera]:  # [h, w, 3] uint8 and the camera of that image
    """The image area-averaged to a registered depth map of lower resolution, the same field of view
    (phone LiDAR, time-of-flight cameras: depth at a fraction of the colour's pixels), and its camera.
    Evidence is made per depth pixel, so each gets the mean colour of its footprint. ValueError
    naming ``depth`` for depth larger than the image or of another shape (another camera's depth)."""
    (h, w), (H, W) = size, rgb.shape[:2]
    problem = depth_size_problem((W, H), (w, h))
    if problem is not None:
        raise ValueError(problem)
    return torch.from_numpy(area_resize(rgb.numpy(), (w, h))), camera.resized(w, h)


@dataclass(frozen=True, eq=False)
class Frame:
    """One posed observation, validated on construction.

    Attributes:
        rgb: uint8 [H, W, 3].
        camera: the frame's `Camera`; its width/height must match the image.
        depth: optional float32 [H, W] z-depth in metres; 0 or non-finite = missing (stored as 0).
            Depth registered to the colour camera at a lower resolution [h, w] (phone LiDAR, time of
            flight) is taken too: the frame's rgb becomes the image area-averaged to h x w and its
            camera that image's (`Camera.resized`), so that evidence is made per depth pixel.
        depth_std: optional float32 [H, W] per-pixel depth standard deviation in metres (>= 0).
        features: optional float32 [H', W', C] client-supplied features at any resolution, spanning
            the image (looked up nearest at its pixels); each pixel's feature vector of norm at most
            `MAX_STORED_VALUE` (float16's largest value).
        labels: optional client-supplied labels: float32 [H', W', S] scores (e.g. class
            probabilities, each of magnitude at most `MAX_STORED_VALUE`), or a class map, integer
            [H', W'] of any integer type (one class id a pixel, negative for none), kept as int16 and
            fused as one-hot scores over ``num_classes`` channels (the same scene as its one-hot
            scores give, without an [H', W', S] array per frame). A pixel whose scores are all 0 (a
            negative id) is no label evidence: a surface only such pixels saw renders no label.
        frame_id: optional free-form identifier.
        num_classes: K of a class map (required with one; None for scores, whose last axis is S).
    """

    rgb: Tensor  # [H, W, 3] uint8
    camera: Camera
    depth: Tensor | None = None  # [H, W] float32
    depth_std: Tensor | None = None  # [H, W] float32
    features: Tensor | None = None  # [H', W', C] float32
    labels: Tensor | None = None  # [H', W', S] float32, or [H', W'] int16 class ids
    frame_id: str | None = None
    num_classes: int | None = None

    def __post_init__(self):
        if not isinstance(self.camera, Camera):
            raise ValueError(f"camera: expected a Camera, got {type(self.camera).__name__}")
        rgb = _tensor(self.rgb, "rgb")
        if rgb.ndim != 3 or rgb.shape[-1] != 3:
            raise ValueError(f"rgb: expected shape [H, W, 3], got {list(rgb.shape)}")
        if rgb.dtype != torch.uint8:
            raise ValueError(f"rgb: expected dtype uint8, got {rgb.dtype}")
        H, W = int(rgb.shape[0]), int(rgb.shape[1])
        if H * W > MAX_IMAGE_PIXELS:
            raise ValueError(f"rgb: image of {W}x{H} pixels exceeds the limit of {MAX_IMAGE_PIXELS} pixels")
        if (self.camera.width, self.camera.height) != (W, H):
            raise ValueError(
                f"camera: size {self.camera.width}x{self.camera.height} does not match the rgb image {W}x{H}"
            )
        # a frame's own principal point lies in its image; outside it, K usually belongs to another
        # image size (e.g. full-resolution K with a downscaled image) and would fuse into the wrong place
        validate_image_intrinsics(self.camera.K64(), W, H, "K", margin=0.0)
        depth_size = _map_size(self.depth)
        if depth_size is not None and depth_size != (H, W):
            rgb, camera = _colour_at_depth_size(rgb, self.camera, depth_size)
            object.__setattr__(self, "camera", camera)
            H, W = depth_size
        object.__setattr__(self, "rgb", rgb.contiguous())
        if self.depth is not None:
            object.__setattr__(self, "depth", _depth_map(self.depth, (H, W)))
        if self.depth_std is not None:
            if self.depth is None:
                raise ValueError("depth_std: given without depth")
            std = _float_map(self.depth_std, "depth_std", (H, W))
            if (std < 0).any():
                raise ValueError("depth_std: negative standard deviations")
            object.__setattr__(self, "depth_std", std)
        if self.features is not None:
            features = _channel_map(self.features, "features", MAX_FEATURE_CHANNELS, mixed=True)
            object.__setattr__(self, "features", features)
        if self.labels is None:
            if self.num_classes is not None:
                raise ValueError("num_classes: given without labels")
        elif (labels := _tensor(self.labels, "labels")).ndim == 2:
            object.__setattr__(self, "labels", _class_map(labels, self.num_classes))
            object.__setattr__(self, "num_classes", int(self.num_classes))
        else:
            labels = _channel_map(labels, "labels", MAX_LABEL_CHANNELS)
            if self.num_classes is not None and self.num_classes != labels.shape[-1]:
                raise ValueError(f"num_classes: {self.num_classes}, but the label scores have {labels.shape[-1]} channels")
            object.__setattr__(self, "labels", labels)
            object.__setattr__(self, "num_classes", None)  # a class map's K only: scores carry theirs
        if self.frame_id is not None:
            if not isinstance(self.frame_id, str):
                raise ValueError(f"frame_id: expected a string, got {type(self.frame_id).__name__}")
            try:  # a lone surrogate (which JSON can carry) is no text: it could be neither logged nor named back
                self.frame_id.encode("utf-8")
            except UnicodeEncodeError as error:
                raise ValueError(f"frame_id: not valid text (a lone surrogate at character {error.start})") from None
            if len(self.frame_id.encode("utf-8", "surrogatepass")) > MAX_FRAME_ID_BYTES:
                raise ValueError(f"frame_id: at most {MAX_FRAME_ID_BYTES} bytes (UTF-8), got "
                                 f"{len(self.frame_id.encode('utf-8', 'surrogatepass'))}")

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def has_depth(self) -> bool:
        return self.depth is not None

    @property
    def label_dim(self) -> int | None:
        """S, the label channels this frame fuses (a class map's ``num_classes``), or None without labels."""
        if self.labels is None:
            return None
        return self.num_classes if self.labels.ndim == 2 else int(self.labels.shape[-1])

    def __repr__(self) -> str:
        extras = [n for n in ("depth", "depth_std", "features", "labels") if getattr(self, n) is not None]
        return f"Frame({self.width}x{self.height}, id={self.frame_id!r}, with={extras}, {self.camera!r})"


def check_rgb_only(frame: Frame, max_pixels: int = MAX_RGB_ONLY_PIXELS) -> None:
    """Raise ValueError naming ``rgb`` when a frame without depth is larger than ``max_pixels``, or
    smaller than `MIN_RGB_ONLY_SIDE` pixels a side (too small to sweep)."""
    if frame.depth is not None:
        return
    if frame.width * frame.height > max_pixels:
        raise ValueError(f"rgb: a frame without depth of {frame.width}x{frame.height} pixels exceeds the limit of "
                         f"{max_pixels} pixels for frames without depth; send depth or a smaller image")
    if min(frame.width, frame.height) < MIN_RGB_ONLY_SIDE:
        raise ValueError(f"rgb: a frame without depth of {frame.width}x{frame.height} pixels is too small to estimate "
                         f"depth from; it needs at least {MIN_RGB_ONLY_SIDE} pixels a side (or send depth)")


def depth_warnings(
    depth: Tensor,  # [H, W] float32 metres, 0 = missing
    near: float,
    far: float,
) -> list[str]:
    """Why a frame's depth gives no usable pixel: none valid, or none within [near, far] (wrong units?).

    Example:
        >>> depth_warnings(torch.zeros(2, 2), 0.1, 10.0)
        ['depth: no valid pixel (all zero, NaN or inf); the frame added nothing']
    """
    valid = depth[depth > 0]
    if valid.numel() == 0:
        return ["depth: no valid pixel (all zero, NaN or inf); the frame added nothing"]
    inside = ((valid > near) & (valid < far)).sum().item()
    if inside == 0:
        median = float(valid.median())
        return [f"depth: no pixel lies within the range {near:g} .. {far:g} m (median {median:g}); "
                f"is the depth in metres (depth_scale)?"]
    return []


def resize_frame(frame: Frame, scale: float) -> Frame:
    """The frame resized by ``scale``: colour area-averaged, depth nearest (no mixing across
    edges or holes), camera via `Camera.scaled`; client features and labels are dropped."""
    if not (isinstance(scale, (int, float)) and 0 < scale <= 1):
        raise ValueError(f"scale: expected a number in (0, 1], got {scale!r}")
    if scale == 1:
        return frame
    camera = frame.camera.scaled(scale)
    size = (camera.width, camera.height)
    rgb = area_resize(frame.rgb.numpy(), size)

    def nearest(t: Tensor | None) -> np.ndarray | None:
        return None if t is None else np.array(Image.fromarray(t.numpy()).resize(size, Image.NEAREST))

    return Frame(rgb=rgb, camera=camera, depth=nearest(frame.depth), depth_std=nearest(frame.depth_std),
                 frame_id=frame.frame_id)
