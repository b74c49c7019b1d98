"""Scene fields from the per-voxel weighted sums: the one place sums become F_scene, colours, moments.

Both the streaming `Scene` and the batch reference `aggregate_batch` produce the same raw sums and
call `fields_from_sums`, so they can only differ in the sums themselves.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .config import KEY_BITS, KEY_OFFSET

SUM_NAMES = ("keys", "rep_r", "rep_f", "rep_pos", "rep_rgb", "r_sum", "f_sum", "rgb_sum", "pos_sum", "pos_sq", "n_obs")
_SQ_INDEX = ((0, 1, 2), (1, 3, 4), (2, 4, 5))  # xx xy xz yy yz zz -> symmetric 3x3


def unpack_keys(keys: Tensor) -> Tensor:  # [V] int64 -> [V, 3] int64 voxel indices (i, j, k)
    mask = (1 << KEY_BITS) - 1
    return torch.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], -1) - KEY_OFFSET


def fields_from_sums(sums: dict[str, np.ndarray | Tensor], voxel_size: float, eps: float, sort: bool = True) -> dict[str, Tensor]:
    """Scene fields from raw sums (rows are voxels; local positions in voxel units).

    Returns a dict of tensors, one row per voxel (sorted by key when ``sort``):
        keys [V] int64, reliability [V] (R_scene = sum W), features [V, L] (F_scene =
        sum W F / (R_scene + eps)), representative_position [V, 3], representative_reliability [V],
        representative_feature [V, L], representative_color [V, 3], color [V, 3] (fused),
        position_mean [V, 3], position_cov [V, 3, 3] (world units), observations [V] int64,
        and labels [V, S] when label scores were fused.
    Colour and position fall back smoothly to the representative's where R_scene ~ 0
    (``(sum W x + eps x_rep) / (R_scene + eps)``), so no voxel decodes to black or to the origin.
    """
    t = {k: torch.as_tensor(v) for k, v in sums.items()}
    if sort:
        order = torch.argsort(t["keys"], stable=True)
        t = {k: v[order] for k, v in t.items()}
    r = t["r_sum"]
    den = (r + eps)[:, None]
    centres = (unpack_keys(t["keys"]).to(torch.float64) + 0.5)
    local_rep = t["rep_pos"].double() / voxel_size - centres  # representative in local voxel units
    mean_local = (t["pos_sum"].double() + eps * local_rep) / den.double()
    sq = t["pos_sq"].double()
    second = torch.stack([torch.stack([sq[:, j] for j in row], -1) for row in _SQ_INDEX], -2)
    second = (second + eps * local_rep[:, :, None] * local_rep[:, None, :]) / den.double()[:, :, None]
    cov_local = second - mean_local[:, :, None] * mean_local[:, None, :]
    out = {
        "keys": t["keys"],
        "reliability": r,
        "features": t["f_sum"] / den,
        "representative_position": t["rep_pos"],
        "representative_reliability": t["rep_r"],
        "representative_feature": t["rep_f"],
        "representative_color": t["rep_rgb"],
        "color": (t["rgb_sum"] + eps * t["rep_rgb"]) / den,
        "position_mean": ((centres + mean_local) * voxel_size).float(),
        "position_cov": (cov_local * voxel_size * voxel_size).float(),
        "observations": t["n_obs"].to(torch.int64),
    }
    if "label_sum" in t and t["label_sum"].shape[1] > 0:
        out["labels"] = t["label_sum"] / (t["label_w"] + eps)[:, None]
    return out
