"""The voxel map's records read as the sums of the stored fields (`stored.StoredRows`): views of a
map's rows, copies of some of them gathered whole, and the parallel byte copy a whole state's copy
takes. The map (`voxel_map`) keeps the records; the decoder side and the snapshot read them so."""

from __future__ import annotations

import numba
import numpy as np

from .decoded import gather_rows
from .stored import StoredRows


def sums_view(
    state: dict[str, np.ndarray],  # a map's arrays (`VoxelMap.state`) or a copy of some of their rows
    stored: StoredRows,  # the stored layout of its records
    n: int,  # rows to view
) -> dict[str, np.ndarray]:
    """The sums of the first ``n`` rows of ``state``, as views: each stored field of the records a
    column (float16 means for the half-precision ones, `stored`)."""
    records = {name: state[name][:n] for name in ("rows", "half")}
    out = {k: v[:n] for k, v in state.items() if k not in records}
    out |= {name: stored.field(records, name) for name in stored.columns}
    if not stored.layout.label_dim:  # the fields' contract: label_sum is [V, 0] without labels
        out["label_sum"] = np.zeros((n, 0), np.float32)
    return out


def gathered_sums(
    state: dict[str, np.ndarray],  # as `sums_view`'s
    stored: StoredRows,
    rows: np.ndarray,  # [N] int64 rows of it
) -> dict[str, np.ndarray]:  # name -> [N, ...]
    """The sums of ``rows`` of ``state``, copied: a gather of whole records (on the numba threads),
    where a gather per column would read each record once per field."""
    return sums_view({k: gather_rows(v, rows).numpy() for k, v in state.items()}, stored, len(rows))


@numba.njit(parallel=True, cache=True)
def copy_bytes(source, out):  # out[:] = source, [B] uint8, in 64 parts on the numba threads
    n = source.shape[0]
    for part in numba.prange(64):
        lo, hi = part * n // 64, (part + 1) * n // 64
        out[lo:hi] = source[lo:hi]
