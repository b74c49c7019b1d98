"""Ext: per-view evidence (features, depth, positional/appearance uncertainty, reliability)."""

from .denoise import denoise_rough_depth, depth_roughness, median_depth
from .extract import FrameEvidence, extract_evidence, observation_sh_basis
from .features import default_features_at, default_features_reference
from .reliability import (AppearanceUncertainty, positional_uncertainty, positional_uncertainty_reference, reliability,
                          sensor_depth_std)
# after extract/reliability: the plane sweep's modules import from those
from .mvs import (DepthRefinement, IdentityRefinement, LogitScale, SelectionRule, SourceView, SourceWindow,
                  complete_depth, depth_range_from_points, estimate_depth, estimate_depth_detailed, select_sources,
                  sensor_holes)
from .mvs_preview import write_depth_previews

__all__ = ["denoise_rough_depth", "depth_roughness", "median_depth", "DepthRefinement", "IdentityRefinement", "LogitScale", "SelectionRule", "SourceView", "SourceWindow",
           "complete_depth", "depth_range_from_points", "estimate_depth", "estimate_depth_detailed", "select_sources", "sensor_holes", "write_depth_previews",
           "FrameEvidence", "extract_evidence", "observation_sh_basis", "default_features_at", "default_features_reference", "AppearanceUncertainty",
           "positional_uncertainty", "positional_uncertainty_reference", "reliability", "sensor_depth_std"]
