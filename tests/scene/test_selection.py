"""Which voxels a decode reads (`scene.selection`): the strongest rows of a level of detail, held to
the stable sort they replaced."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from canonical_core.scene.selection import strongest


@pytest.mark.parametrize("values", ["distinct", "many ties"])
def test_a_level_of_detail_picks_what_a_stable_descending_sort_would(values):
    # `strongest` replaced a stable argsort of every decoded row's support, taken under the scene's
    # lock, by a partition: the same rows in the same order, ties at the cut to the lower index
    rng = np.random.default_rng(7)
    for _ in range(500):
        n, count = int(rng.integers(0, 80)), int(rng.integers(-2, 90))
        support = (rng.integers(0, 4, n) if values == "many ties" else rng.random(n)).astype(np.float32)
        reference = torch.sort(torch.argsort(torch.from_numpy(support), descending=True, stable=True)[:max(count, 0)]).values
        picked = strongest(support.copy(), count)
        assert picked.dtype == np.int64 and np.array_equal(picked, reference.numpy()), (support, count)
