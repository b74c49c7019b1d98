"""Evaluation: metrics, protocols and baselines (the classical peer lives in `open3d_tsdf`)."""
