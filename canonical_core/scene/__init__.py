"""Agg: the sparse voxel scene (streaming fold, batch reference, fields, persistence)."""

from .batch import aggregate_batch
from .config import SceneConfig
from .scene import CapacityError, DecodeInputs, FoldReport, Scene

__all__ = ["CapacityError", "DecodeInputs", "FoldReport", "Scene", "SceneConfig", "aggregate_batch"]
