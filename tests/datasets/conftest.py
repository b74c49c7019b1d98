"""Shared fixtures: the real captures in ../shared/data (skipped when absent) and small written ones."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from canonical_core import Frame
from canonical_core.datasets import load_tsdf_fusion, load_tum, synthetic_rgbd, write_tsdf_fusion

from ..conftest import DATA, require_capture

SHELF = DATA / "realsense_shelf"
SLAMBOOK = DATA / "slambook_rgbd5"
HOLOLENS = DATA / "hololens_office"
LIVINGROOM = DATA / "livingroom_synthetic"
SLAMBOOK_K = (518.0, 519.0, 325.5, 253.5)  # from the data README; not stored in the capture


@pytest.fixture(scope="session")
def shelf_path() -> Path:
    return require_capture(SHELF)


@pytest.fixture(scope="session")
def slambook_path() -> Path:
    return require_capture(SLAMBOOK)


@pytest.fixture(scope="session")
def hololens_path() -> Path:
    return require_capture(HOLOLENS)


@pytest.fixture(scope="session")
def livingroom_path() -> Path:
    return require_capture(LIVINGROOM)


@pytest.fixture(scope="session")
def slambook_K() -> tuple[float, float, float, float]:
    return SLAMBOOK_K


@pytest.fixture(scope="session")
def shelf(shelf_path):
    return load_tsdf_fusion(shelf_path)


@pytest.fixture(scope="session")
def slambook(slambook_path):
    return load_tum(slambook_path, K=SLAMBOOK_K)


@pytest.fixture(scope="session")
def tiny_tsdf(tmp_path_factory) -> Path:
    """A 3-frame, 64x48 tsdf-fusion folder written from the synthetic sample (read-only: copy it to mutate)."""
    return write_tsdf_fusion(synthetic_rgbd(num_frames=3, width=64, height=48), tmp_path_factory.mktemp("tiny") / "cap")


@pytest.fixture(scope="session")
def reprojection_error():
    return _reprojection_error


def _reprojection_error(src: Frame, dst: Frame) -> tuple[float, int]:
    """Lift src's valid depth with its pose, project into dst, compare with dst's depth at the
    nearest pixel: (median |error| in metres, number of compared pixels)."""
    v, u = torch.nonzero(src.depth > 0, as_tuple=True)
    points = src.camera.lift(torch.stack([u, v], -1).float(), src.depth[v, u])
    uv, z = dst.camera.project(points)
    ui, vi = uv[:, 0].round().long(), uv[:, 1].round().long()
    inside = (z > 0) & (ui >= 0) & (ui < dst.width) & (vi >= 0) & (vi < dst.height)
    observed = dst.depth[vi[inside], ui[inside]]
    valid = observed > 0
    error = (observed[valid] - z[inside][valid]).abs()
    return float(error.median()), int(valid.sum())
