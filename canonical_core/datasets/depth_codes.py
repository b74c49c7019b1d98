"""16-bit depth codes to metres, compiled (`files.depth_from_uint16`).

In a module of its own, imported on the first conversion, so that listing a capture does not load
numba (`sequence`).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def metres_kernel(
    raw,  # [P] uint16 codes
    depth_scale,  # float64 codes per metre
    invalid,  # the code that marks a missing depth besides 0
    out,  # [P] float32 metres, written
):
    for i in range(raw.shape[0]):
        value = raw[i]
        out[i] = 0.0 if value == 0 or value == invalid else np.float32(np.float64(value) / depth_scale)
