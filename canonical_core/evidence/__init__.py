"""Ext: per-view evidence (features, depth, positional/appearance uncertainty, reliability), and
depth for frames without it (the plane sweep) or with holes in it (completion)."""

from .completion import complete_depth, sensor_holes
from .consistency import DepthConsistency, compare_depth, inconsistent_below
from .denoise import denoise_rough_depth, depth_roughness, median_depth
from .extract import FrameEvidence, extract_evidence, observation_sh_basis
from .features import default_features_at, default_features_reference
from .mvs import DepthRefinement, IdentityRefinement, depth_range_from_points, estimate_depth, estimate_depth_detailed
from .reliability import (AppearanceUncertainty, positional_uncertainty, positional_uncertainty_reference, reliability,
                          sensor_depth_std)
from .source_views import SelectionRule, SourceView, SourceWindow, select_sources

__all__ = ["DepthConsistency", "compare_depth", "inconsistent_below", "denoise_rough_depth", "depth_roughness", "median_depth", "DepthRefinement", "IdentityRefinement", "SelectionRule", "SourceView", "SourceWindow",
           "complete_depth", "depth_range_from_points", "estimate_depth", "estimate_depth_detailed", "select_sources", "sensor_holes",
           "FrameEvidence", "extract_evidence", "observation_sh_basis", "default_features_at", "default_features_reference", "AppearanceUncertainty",
           "positional_uncertainty", "positional_uncertainty_reference", "reliability", "sensor_depth_std"]
