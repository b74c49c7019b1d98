"""Agg, batch reference: the paper's rule over all observations at once (pure PyTorch).

For the observations Omega(v) of voxel v (all frames, in frame order then pixel order):
    representative (i*, m*) = argmax R_view          (first maximum wins)
    W = R_view(m) * max(0, cos(F(m), F(m*)))
    R_scene(v) = sum W,   F_scene(v) = sum W F / (R_scene + eps)
and the same W accumulate colour, position moments and label scores. Ablation modes:
``no_reliability`` (R := 1: W = max(0, cos), representative = first observation),
``no_similarity`` (W = R), ``average`` (W = 1, representative = first observation).
Kept for tests, ablations and evaluation; the service uses the streaming `Scene.fold`.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor

from ..evidence import AppearanceUncertainty, extract_evidence
from ..frame import Frame
from .config import KEY_BITS, KEY_OFFSET, SceneConfig
from .fields import fields_from_sums


def voxel_keys(points: Tensor, voxel_size: float) -> Tensor:  # [M, 3] float32 -> [M] int64, -1 outside
    """Packed lattice keys of floor(x / voxel_size) (21 bits per axis around a fixed origin)."""
    ijk = torch.floor(points * torch.tensor(1.0 / voxel_size, dtype=torch.float32)).to(torch.int64) + KEY_OFFSET
    inside = ((ijk >= 0) & (ijk < (1 << KEY_BITS))).all(-1)
    keys = (ijk[:, 0] << (2 * KEY_BITS)) | (ijk[:, 1] << KEY_BITS) | ijk[:, 2]
    return torch.where(inside, keys, torch.full_like(keys, -1))


def aggregate_batch(
    frames: Iterable[Frame],
    config: SceneConfig,
    appearance: AppearanceUncertainty | None = None,
) -> dict[str, Tensor]:
    """The batch rule over ``frames``; returns the same fields as `Scene.fields` (sorted by key)."""
    evidence = [extract_evidence(f, config, appearance) for f in frames]
    if not evidence:
        raise ValueError("frames: expected at least one frame")
    L = config.feature_dim
    points = torch.from_numpy(np.concatenate([e.points for e in evidence]))
    rel = torch.from_numpy(np.concatenate([e.reliability for e in evidence]))
    feat = torch.from_numpy(np.concatenate([e.features for e in evidence]))
    rgb = torch.from_numpy(np.concatenate([e.colors for e in evidence]))
    label_dims = {e.labels.shape[1] for e in evidence if e.labels is not None}
    if len(label_dims) > 1:
        raise ValueError(f"labels: frames carry different label channel counts {sorted(label_dims)}")
    S = label_dims.pop() if label_dims else 0
    labels = torch.from_numpy(np.concatenate(
        [e.labels if e.labels is not None else np.zeros((len(e), S), np.float32) for e in evidence]))
    has_label = torch.from_numpy(np.concatenate([np.full(len(e), e.labels is not None) for e in evidence]))

    keys = voxel_keys(points, config.voxel_size)
    inside = keys >= 0
    points, rel, feat, rgb, labels, has_label, keys = (t[inside] for t in (points, rel, feat, rgb, labels, has_label, keys))
    uniq, inv = torch.unique(keys, return_inverse=True)
    V, M = uniq.numel(), keys.numel()

    uses_rel = config.weighting in ("full", "no_similarity")
    uses_sim = config.weighting in ("full", "no_reliability")
    r_sel = rel if uses_rel else torch.ones_like(rel)
    best = torch.full((V,), -1.0).scatter_reduce(0, inv, r_sel, "amax")
    order = torch.arange(M)
    rep = torch.full((V,), M, dtype=torch.int64).scatter_reduce(
        0, inv, torch.where(r_sel == best[inv], order, torch.full_like(order, M)), "amin")

    w = r_sel.clone()
    if uses_sim:
        cos = torch.nn.functional.cosine_similarity(feat, feat[rep][inv], dim=-1, eps=1e-10)
        w = w * cos.clamp_min(0.0)
    # local positions in voxel units, relative to the voxel centre (as the streaming kernel)
    scaled = points * torch.tensor(1.0 / config.voxel_size, dtype=torch.float32)
    local = scaled - (torch.floor(scaled) + 0.5)
    sq = torch.stack([local[:, a] * local[:, b] for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))], -1)

    def wsum(x: Tensor) -> Tensor:
        x2 = x if x.ndim == 2 else x[:, None]
        out = torch.zeros((V, x2.shape[1]), dtype=torch.float32).index_add_(0, inv, w[:, None] * x2)
        return out if x.ndim == 2 else out[:, 0]

    lw = torch.where(has_label, w, torch.zeros_like(w))
    sums = {
        "keys": uniq,
        "rep_r": r_sel[rep],
        "rep_f": feat[rep],
        "rep_pos": points[rep],
        "rep_rgb": rgb[rep],
        "r_sum": wsum(torch.ones(M)),
        "f_sum": wsum(feat) if L else torch.zeros(V, 0),
        "rgb_sum": wsum(rgb),
        "pos_sum": wsum(local),
        "pos_sq": wsum(sq),
        "n_obs": torch.bincount(inv, minlength=V).to(torch.int32),
        "label_sum": torch.zeros((V, S)).index_add_(0, inv, lw[:, None] * labels),
        "label_w": torch.zeros(V).index_add_(0, inv, lw),
    }
    return fields_from_sums(sums, config.voxel_size, config.eps, sort=True)
