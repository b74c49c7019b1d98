"""Agg, batch reference: the aggregation rule over all observations at once (pure PyTorch).

For the observations Omega(v) of voxel v (all frames, in frame order then pixel order):
    representative (i*, m*) = argmax R_view          (first maximum wins)
    W = max(R_view(m) * max(0, cos(F(m), F(m*))), weight_floor * R_view(m*))
      (F(m*) as the map keeps it: its 8-bit direction, `stored.quantize_direction`)
    R_scene(v) = sum W,   F_scene(v) = sum W F / (R_scene + eps)
and the same W accumulate colour, position moments and label scores. Ablation modes:
``no_reliability`` (R := 1: W = max(0, cos), representative = first observation),
``no_similarity`` (W = R), ``average`` (W = 1, representative = first observation).
Free-space evidence is summed over every (voxel, frame) pair with `see_through_reference`, the
PyTorch definition of the test the streaming kernels apply.
Kept for tests, ablations and evaluation; the service uses the streaming `Scene.fold`.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch
from torch import Tensor

from ..evidence import AppearanceUncertainty, extract_evidence, observation_sh_basis
from ..frame import Frame
from ..config import KEY_BITS, KEY_OFFSET, SceneConfig
from .choices import choose_settings
from .fields import fields_from_sums, unpack_keys
from .stored import directions_of
from .free_space import SeeThroughMap, see_through_map


def voxel_keys(points: Tensor, voxel_size: float) -> Tensor:  # [M, 3] float32 -> [M] int64, -1 outside
    """Packed lattice keys of floor(x / voxel_size) (21 bits per axis around a fixed origin)."""
    ijk = torch.floor(points * torch.tensor(1.0 / voxel_size, dtype=torch.float32)).to(torch.int64) + KEY_OFFSET
    inside = ((ijk >= 0) & (ijk < (1 << KEY_BITS))).all(-1)
    keys = (ijk[:, 0] << (2 * KEY_BITS)) | (ijk[:, 1] << KEY_BITS) | ijk[:, 2]
    return torch.where(inside, keys, torch.full_like(keys, -1))


def see_through_reference(
    centres: Tensor,  # [V, 3] voxel centres, world
    m: SeeThroughMap,
    near: float,
) -> Tensor:  # [V] see-through evidence of one frame
    """Evidence a frame's see-through map gives each voxel centre (0 where it is not seen through)."""
    P = torch.from_numpy(m.w2c)
    # each camera coordinate in the kernel's order of operations, not as a matrix product (whose
    # summation order depends on the BLAS build): a centre on a cell's edge or at the threshold
    # then lands on the same side in both
    pc = torch.stack([P[r, 0] * centres[:, 0] + P[r, 1] * centres[:, 1] + P[r, 2] * centres[:, 2] + P[r, 3]
                      for r in range(3)], 1)
    z = pc[:, 2]
    safe = torch.where(z > near, z, torch.ones_like(z))
    fx, fy, cx, cy = torch.from_numpy(m.intrinsics)
    iu = torch.floor(fx * pc[:, 0] / safe + cx + 0.5).long()
    iv = torch.floor(fy * pc[:, 1] / safe + cy + 0.5).long()
    h, w = m.threshold.shape
    inside = (z > near) & (iu >= 0) & (iv >= 0) & (iu < w) & (iv < h)
    iu, iv = iu.clamp(0, w - 1), iv.clamp(0, h - 1)
    thr = torch.from_numpy(m.threshold)[iv, iu]
    seen = inside & (thr > 0) & (z < thr)
    return torch.where(seen, torch.from_numpy(m.weight)[iv, iu] * m.area_scale / (safe * safe), torch.zeros_like(z))


def aggregate_batch(
    frames: Iterable[Frame],
    config: SceneConfig,
    appearance: AppearanceUncertainty | None = None,
) -> dict[str, Tensor]:
    """The batch rule over ``frames``; returns the same fields as `Scene.fields` (sorted by key).
    What ``config`` leaves open is chosen from the first frame, as a `Scene` does (`choices`)."""
    frames = list(frames)
    if not frames:
        raise ValueError("frames: expected at least one frame")
    config = config if config.chosen else choose_settings(config, frames[0])[0]
    evidence = [extract_evidence(f, config, appearance) for f in frames]
    L = config.features.dim
    points = torch.from_numpy(np.concatenate([e.points for e in evidence]))
    rel = torch.from_numpy(np.concatenate([e.reliability for e in evidence]))
    feat = torch.from_numpy(np.concatenate([e.features for e in evidence]))
    rgb = torch.from_numpy(np.concatenate([e.colors for e in evidence]))
    basis = torch.from_numpy(np.concatenate([observation_sh_basis(e, f.camera, config.sh_degree) for e, f in zip(evidence, frames)]))
    label_dims = {e.labels.shape[1] for e in evidence if e.labels is not None}
    if len(label_dims) > 1:
        raise ValueError(f"labels: frames carry different label channel counts {sorted(label_dims)}")
    S = label_dims.pop() if label_dims else 0
    labels = torch.from_numpy(np.concatenate(
        [e.labels if e.labels is not None else np.zeros((len(e), S), np.float32) for e in evidence]))
    has_label = labels.ne(0).any(-1)  # a row of zeros (no class; a frame without labels) is no label evidence

    keys = voxel_keys(points, config.voxel_size)
    inside = keys >= 0
    points, rel, feat, rgb, basis, labels, has_label, keys = (
        t[inside] for t in (points, rel, feat, rgb, basis, labels, has_label, keys))
    uniq, inv = torch.unique(keys, return_inverse=True)
    V, M = uniq.numel(), keys.numel()

    uses_rel, uses_sim = config.uses_reliability, config.uses_similarity
    r_sel = rel if uses_rel else torch.ones_like(rel)
    best = torch.full((V,), -1.0).scatter_reduce(0, inv, r_sel, "amax")
    order = torch.arange(M)
    rep = torch.full((V,), M, dtype=torch.int64).scatter_reduce(
        0, inv, torch.where(r_sel == best[inv], order, torch.full_like(order, M)), "amin")

    rep_dir = torch.from_numpy(directions_of(feat[rep].numpy())).float()  # the representative as kept (`stored`)
    w = r_sel.clone()
    if uses_sim:
        cos = torch.nn.functional.cosine_similarity(feat, rep_dir[inv], dim=-1, eps=1e-10)
        w = w * cos.clamp_min(0.0)
    w = torch.maximum(w, config.sensor.weight_floor * best[inv])  # the floor: a share of the voxel's best reliability
    # local positions in voxel units, relative to the voxel centre (as the streaming kernel)
    scaled = points * torch.tensor(1.0 / config.voxel_size, dtype=torch.float32)
    local = scaled - (torch.floor(scaled) + 0.5)
    sq = torch.stack([local[:, a] * local[:, b] for a, b in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))], -1)

    def wsum(x: Tensor) -> Tensor:
        x2 = x if x.ndim == 2 else x[:, None]
        out = torch.zeros((V, x2.shape[1]), dtype=torch.float32).index_add_(0, inv, w[:, None] * x2)
        return out if x.ndim == 2 else out[:, 0]

    lw = torch.where(has_label, w, torch.zeros_like(w))
    k = basis.shape[1] if config.sh_degree > 0 else 1
    rows, cols = torch.triu_indices(k, k)
    free = torch.zeros(V)
    if config.free_space.enabled:
        centres = (unpack_keys(uniq).float() + 0.5) * torch.tensor(config.voxel_size, dtype=torch.float32)
        for f in frames:
            free += see_through_reference(centres, see_through_map(f, config), config.range.near)
    sums = {
        "keys": uniq,
        "rep_r": r_sel[rep],
        "rep_f": rep_dir,
        "rep_pos": local[rep],
        "rep_rgb": torch.round(rgb[rep] * 255.0).to(torch.uint8),
        "r_sum": wsum(torch.ones(M)),
        "f_sum": wsum(feat) if L else torch.zeros(V, 0),
        "rgb_sum": wsum(rgb),
        "pos_sum": wsum(local),
        "pos_sq": wsum(sq),
        "sh_a": wsum(basis[:, rows[1:]] * basis[:, cols[1:]]),
        "sh_b": wsum((basis[:, 1:, None] * (rgb - 0.5)[:, None, :]).reshape(M, -1)),
        "free": free,
        "n_obs": torch.bincount(inv, minlength=V).to(torch.int32),
        "label_sum": torch.zeros((V, S)).index_add_(0, inv, lw[:, None] * labels),
        "label_w": torch.zeros(V).index_add_(0, inv, lw),
    }
    return fields_from_sums(sums, config, sort=True)
