"""Loaders for common capture layouts, and a generated sample.

- `load_tsdf_fusion`: tsdf-fusion / 7-Scenes (``frame-NNNNNN.color.png / .depth.png / .pose.txt``)
- `load_tum`: TUM RGB-D (rgb.txt / depth.txt / groundtruth.txt) and slambook (pose.txt, color/, depth/)
- `load_transforms_json`: nerfstudio / instant-ngp ``transforms.json`` (OpenGL poses, distortion)
- `load_deep_video_mvs`: deep-video-mvs (``K.txt``, ``poses.txt``, ``images/``, ``depth/``)
- `load_redwood`: Redwood / Open3D reconstruction system (``image/``, ``depth/``, ``trajectory.log``)
- `load_label_fusion`: label-fusion's bins (tsdf-fusion frames, bit-rotated depth, label maps as labels)
- `load_dataset`: detects which of the above a path holds
- `synthetic_rgbd`: an exactly ray-cast scene of textured boxes; `write_tsdf_fusion` saves any frames

All return a `FrameSequence`: frames read lazily on indexing, slicing without reading, and
``frame_ids`` without reading images. Poses come out camera-to-world in OpenCV axes, depth in
metres (0 = missing), as DESIGN.md prescribes. A listed frame whose images are missing is left out
with one `SkippedFrames` warning (``strict=True`` refuses the capture instead).

Example:
    >>> from canonical_core.datasets import synthetic_rgbd
    >>> seq = synthetic_rgbd(num_frames=8, width=64, height=48)
    >>> frame = seq[-1]
    >>> frame.rgb.shape, frame.camera.width
    (torch.Size([48, 64, 3]), 64)
"""

from .deep_video_mvs import load_deep_video_mvs
from .detect import UnknownLayout, load_dataset
from .files import MissingIntrinsics, SkippedFrames
from .label_fusion import load_label_fusion
from .redwood import load_redwood
from .sequence import FrameSequence
from .synthetic import synthetic_rgbd
from .transforms_json import load_transforms_json
from .tsdf_fusion import load_tsdf_fusion, write_tsdf_fusion
from .tum import load_tum

__all__ = [
    "FrameSequence",
    "MissingIntrinsics",
    "SkippedFrames",
    "UnknownLayout",
    "load_dataset",
    "load_deep_video_mvs",
    "load_label_fusion",
    "load_redwood",
    "load_transforms_json",
    "load_tsdf_fusion",
    "load_tum",
    "synthetic_rgbd",
    "write_tsdf_fusion",
]
