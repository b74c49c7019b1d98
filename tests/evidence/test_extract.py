import numpy as np
import pytest

from canonical_core.evidence.extract import valid_depth_pixels


@pytest.mark.parametrize("shape", [(1, 1), (7, 13), (48, 64)])
def test_valid_depth_pixels_is_nonzero_of_the_range_mask_in_row_major_order(shape):
    rng = np.random.default_rng(sum(shape))
    depth = (rng.random(shape) * 6.0).astype(np.float32)
    depth[rng.random(shape) < 0.3] = 0.0  # holes
    depth[rng.random(shape) < 0.05] = np.nan  # NaN is never in range
    depth[0] = 0.0  # a row without one valid pixel (the parallel prefix sum must skip it)
    near, far = np.float32(0.5), np.float32(5.0)
    rows, cols = valid_depth_pixels(depth, near, far)
    with np.errstate(invalid="ignore"):
        expected_rows, expected_cols = np.nonzero((depth > near) & (depth < far))
    assert rows.dtype == cols.dtype == np.int64
    assert np.array_equal(rows, expected_rows) and np.array_equal(cols, expected_cols)
