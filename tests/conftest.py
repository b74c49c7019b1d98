"""Fixtures shared across the suite: the real captures in ../shared/data (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_DATA_FIXTURES = {"shelf_dir", "shelf_path", "slambook_path", "hololens_path", "livingroom_path", "apc_bins_path"}  # every fixture that reads ../shared/data


def pytest_collection_modifyitems(items):
    """A test that reaches a real capture through a fixture carries the ``realdata`` marker, whether or
    not its module says so, so ``-m "not realdata"`` is exactly the unit tests on generated data."""
    for item in items:
        if REAL_DATA_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.realdata)


def require_capture(path: Path) -> Path:
    """``path`` (a capture in ../shared/data), or the test skipped where the data is not there."""
    if not path.is_dir():
        pytest.skip(f"real capture not found at {path} (../shared/data is optional)")
    return path


@pytest.fixture(scope="session")
def shelf_dir() -> Path:
    return require_capture(DATA / "realsense_shelf")


@pytest.fixture(scope="session")
def apc_bins_path() -> Path:
    """The two labelled shelf bins (``bin_labels``, ``bin_mask``: 15 RealSense frames each)."""
    return require_capture(DATA / "apc_bins")


@pytest.fixture(scope="session")
def shelf_frames(shelf_dir) -> list[Frame]:
    """All 50 shelf frames (640x480, sensor depth), loaded once."""
    from canonical_core.datasets import load_tsdf_fusion

    return list(load_tsdf_fusion(shelf_dir))


def solved_as_kept(gaussians, views, start=None, **settings):
    """`decode.solve_colours` of ``gaussians`` (``colour_offsets(gaussians, views, start, **settings)``
    added), its offsets rounded as a scene keeps them (`scene.decoding.ColourSolution`: float16):
    what a scene's decode shows of the same solve."""
    from canonical_core.decode import colour_offsets, with_colour_offsets

    return with_colour_offsets(gaussians, colour_offsets(gaussians, views, start, **settings).half())


def folded_scene(frames, voxel_size: float = 0.008, **settings):
    """A `Scene` (``SceneConfig(voxel_size, **settings)``) that has folded ``frames`` in order."""
    from canonical_core import Scene, SceneConfig

    scene = Scene(SceneConfig(voxel_size=voxel_size, **settings))
    for frame in frames:
        scene.fold(frame)
    return scene


def make_frame(depth, rgb=None, features=None, depth_std=None, labels=None, fx=1.0, c2w=None) -> Frame:
    """A small hand-made frame: pixel (u, v) lifts to ((u - cx) z / fx, (v - cy) z / fx, z), cx = cy = 0."""
    depth = np.asarray(depth, np.float32)
    h, w = depth.shape
    rgb = np.full((h, w, 3), 128, np.uint8) if rgb is None else np.asarray(rgb, np.uint8)
    cam = Camera(K=[[fx, 0, 0], [0, fx, 0], [0, 0, 1]], c2w=np.eye(4) if c2w is None else c2w, width=w, height=h)
    as_t = lambda a: None if a is None else torch.as_tensor(np.asarray(a, np.float32))  # noqa: E731
    return Frame(rgb=rgb, camera=cam, depth=depth, depth_std=as_t(depth_std), features=as_t(features), labels=as_t(labels))
