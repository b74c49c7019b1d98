"""Agg: the sparse voxel scene (streaming fold, batch reference, fields, persistence)."""

from .batch import aggregate_batch
from .config import SceneConfig
from .scene import CapacityError, FoldReport, Scene

__all__ = ["CapacityError", "FoldReport", "Scene", "SceneConfig", "aggregate_batch"]
