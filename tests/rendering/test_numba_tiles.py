"""Pieces of the numba backend held to numpy (the images are held to the reference in test_renderer)."""

import numpy as np
import pytest

from canonical_core.rendering.numba_tiles import stable_depth_order


@pytest.mark.parametrize("n", [0, 1, 2, 7, 1000, 20000])
def test_stable_depth_order_equals_numpy_stable_argsort(n):
    # few distinct depths (many ties: input order must be kept) spread over several float exponents
    rng = np.random.default_rng(n)
    depths = rng.choice(rng.uniform(0.01, 300.0, max(n // 4, 1)), n).astype(np.float32)
    assert np.array_equal(stable_depth_order(depths), np.argsort(depths, kind="stable"))


def test_stable_depth_order_of_equal_depths_is_the_identity():
    assert np.array_equal(stable_depth_order(np.full(300, 2.5, np.float32)), np.arange(300))
