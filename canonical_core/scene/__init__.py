"""Agg: the sparse voxel scene. `Scene` is a facade over the depth front end (`depth_frontend`), the
voxel map (`voxel_map`), integration (`integrate`, `free_space`) and the decoder side (`decoding`);
`aggregate_batch` is the batch reference of the aggregation rule."""

from .batch import aggregate_batch
from ..config import SceneConfig
from .integrate import release_scratch
from .scene import CapacityError, DecodeInputs, FoldReport, PreparedFrame, Scene

__all__ = ["CapacityError", "DecodeInputs", "FoldReport", "PreparedFrame", "Scene", "SceneConfig", "aggregate_batch",
           "release_scratch"]
