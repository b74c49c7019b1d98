"""Ext: per-view evidence (features, depth, positional/appearance uncertainty, reliability)."""

from .extract import FrameEvidence, extract_evidence, observation_sh_basis
from .features import default_features_at, default_features_reference
from .reliability import AppearanceUncertainty, positional_uncertainty, positional_uncertainty_reference, reliability

__all__ = ["FrameEvidence", "extract_evidence", "observation_sh_basis", "default_features_at", "default_features_reference", "AppearanceUncertainty",
           "positional_uncertainty", "positional_uncertainty_reference", "reliability"]
