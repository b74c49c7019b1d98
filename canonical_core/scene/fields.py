"""Scene fields from the per-voxel weighted sums: the one place sums become F_scene, colours, moments.

Both the streaming `Scene` and the batch reference `aggregate_batch` produce the same raw sums and
call `fields_from_sums`, so they can only differ in the sums themselves.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..gaussians.container import SH_C0
from .config import KEY_BITS, KEY_OFFSET, SceneConfig

_SQ_INDEX = ((0, 1, 2), (1, 3, 4), (2, 4, 5))  # xx xy xz yy yz zz -> symmetric 3x3


def unpack_keys(keys: Tensor) -> Tensor:  # [V] int64 -> [V, 3] int64 voxel indices (i, j, k)
    mask = (1 << KEY_BITS) - 1
    return torch.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], -1) - KEY_OFFSET


def sh_sum_widths(degree: int) -> tuple[int, int]:
    """Columns of the SH normal-equation sums: (upper triangle of sum W b b^T without (0, 0), sum W b (c - 1/2) rows k >= 1)."""
    k = (degree + 1) ** 2
    return k * (k + 1) // 2 - 1, 3 * (k - 1)


def solve_sh(
    r: Tensor,  # [V] R_scene (+ eps)
    color_sum: Tensor,  # [V, 3] sum W c (+ eps * representative colour)
    sh_a: Tensor,  # [V, K(K+1)/2 - 1]
    sh_b: Tensor,  # [V, 3 (K - 1)]
    regularization: float,
) -> Tensor:  # [V, K, 3]
    """Per-voxel least-squares SH colour fit from the streamed normal equations.

    Minimises sum W |c - 1/2 - sh^T b(d)|^2 + regularization * R_scene * |sh_{k>=1}|^2: a ridge that
    pulls the view-dependent terms toward zero (the DC colour) where few directions were seen.
    """
    k = sh_b.shape[1] // 3 + 1
    V = r.shape[0]
    A = torch.zeros((V, k, k), dtype=torch.float64)
    A[:, 0, 0] = SH_C0 * SH_C0 * r.double()
    rows, cols = torch.triu_indices(k, k)
    A[:, rows[1:], cols[1:]] = sh_a.double()
    A = A + torch.triu(A, 1).transpose(1, 2)
    diag = torch.arange(1, k)
    A[:, diag, diag] += regularization * r.double()[:, None]
    B = torch.cat([(SH_C0 * (color_sum.double() - 0.5 * r.double()[:, None]))[:, None], sh_b.double().reshape(V, k - 1, 3)], 1)
    return torch.linalg.solve(A, B).float()


def fields_from_sums(sums: dict[str, np.ndarray | Tensor], config: SceneConfig, sort: bool = True) -> dict[str, Tensor]:
    """Scene fields from raw sums (rows are voxels; local positions in voxel units).

    Returns a dict of tensors, one row per voxel (sorted by key when ``sort``):
        keys [V] int64, reliability [V] (R_scene = sum W), features [V, L] (F_scene =
        sum W F / (R_scene + eps)), representative_position [V, 3], representative_reliability [V],
        representative_feature [V, L], representative_color [V, 3], color [V, 3] (fused),
        position_mean [V, 3], position_cov [V, 3, 3] (world units), observations [V] int64,
        free_space [V] (see-through evidence, in R_scene's unit), sh [V, K, 3] (the solved SH colour
        fit, K = (sh_degree + 1)^2), and labels [V, S] when label scores were fused.
    Colour and position fall back smoothly to the representative's where R_scene ~ 0
    (``(sum W x + eps x_rep) / (R_scene + eps)``), so no voxel decodes to black or to the origin.
    """
    voxel_size, eps = config.voxel_size, config.eps
    t = {k: torch.as_tensor(v) for k, v in sums.items()}
    t["rep_rgb"] = t["rep_rgb"].float() / 255.0  # stored as the 8-bit input colour
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
    color_sum = t["rgb_sum"] + eps * t["rep_rgb"]
    out = {
        "keys": t["keys"],
        "reliability": r,
        "features": t["f_sum"] / den,
        "representative_position": t["rep_pos"],
        "representative_reliability": t["rep_r"],
        "representative_feature": t["rep_f"],
        "representative_color": t["rep_rgb"],
        "color": color_sum / den,
        "position_mean": ((centres + mean_local) * voxel_size).float(),
        "position_cov": (cov_local * voxel_size * voxel_size).float(),
        "observations": t["n_obs"].to(torch.int64),
        "free_space": t["free"],
        "sh": solve_sh(r + eps, color_sum, t["sh_a"], t["sh_b"], config.sh_regularization),
    }
    if t["label_sum"].shape[1] > 0:
        out["labels"] = t["label_sum"] / (t["label_w"] + eps)[:, None]
    return out
