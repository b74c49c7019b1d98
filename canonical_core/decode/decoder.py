"""Dec: scene fields -> 3D Gaussians, initialised at an analytic solution.

For each voxel with support:
    r        = 1 - exp(-R_scene / R_unit),   q = free / (free + R_scene)  (share of rays that saw through)
    opacity  = sigmoid(support(r) - penalty(q))       (support, penalty: monotone heads, so opacity is
                                                       non-decreasing in R_scene and non-increasing in
                                                       free-space evidence for any parameters)
    mean     = weighted centroid of the lifted points + voxel_size * offset(F_scene)
    Sigma    = weighted second moments of the lifted points, per-axis std scaled by the footprint
               gain and clamped to the voxel scale, then refined by a log-scale delta(F_scene)
    colour   = streamed SH fit (DC = fused colour at degree 0) + delta(F_scene) on the DC term
The heads on F_scene start at zero, so an untrained decoder is the analytic solution; support(r)
starts as the line 3 r and penalty(q) as 4 q (how the line reads: `SceneConfig.decoder.opacity_slope`).

Mean. The analytic offset is the one that moves the representative's lifted point to the centroid
sum W x / R_scene of the voxel's lifted points: the covariance is the second moment about that
centroid, so a Gaussian at the representative would be shifted off its own point cloud by up to a
voxel, and the centroid averages the depth noise of every folded observation instead of keeping
one sample's.

R_unit is the scene's typical weight of one observation (`support_unit`): support is counted in
"typical observations", so a capture whose every reliability is low (a noisy depth sensor, a far
scene) is not rendered see-through as a whole; within a scene, opacity still grows with R_scene.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from ..gaussians import SH_C0, Gaussians, rgb_to_sh_dc
from .eigen import symmetric_eigh3, symmetric_eigh3_reference

# A Gaussian whose integral footprint 2*pi*sigma^2 equals the area a^2 of the patch it stands for has
# sigma = a / sqrt(2 pi); the patch's own std is a / sqrt(12). Scaling moment-stds by the ratio turns
# the spread of a voxel's points into the Gaussian's (it sets the thickness along the normal).
FOOTPRINT_GAIN = math.sqrt(12.0 / (2.0 * math.pi))
# The smallest in-plane std, in voxels. Two face-neighbours covering a surface must both still be
# opaque at the face they share, or the surface shows see-through seams: at sigma = 1/2 voxel each
# keeps exp(-1/2) = 61 % of its peak alpha there, so two fully supported neighbours let at most
# (1 - 0.61)^2 = 15 % through (the equal-area 1/sqrt(2 pi) would keep 46 % each and let 29 % through,
# which shows as speckle on real captures). Points inside a voxel never spread wider than this, so in-plane
# extents are this clamp and the moments set the orientation and the thickness.
FULL_VOXEL_EXTENT = 0.5
# The analytic opacity line a r + b (how it reads: `SceneConfig.decoder.opacity_slope`, whose defaults are
# these).
OPACITY_SLOPE, OPACITY_BIAS = 3.0, 0.0


class MonotoneOpacity(nn.Module):
    """logit(r) = a r + b + sum_k w_k tanh(u_k r + c_k) with a, w_k, u_k >= 0 (clamped in forward).

    Non-negativity is enforced in the forward pass, so the map is non-decreasing in r for *any*
    parameter values (a property under test). At initialisation w_k = 0, so it is the analytic
    line a r + b; training can bend it.
    """

    def __init__(self, slope: float = OPACITY_SLOPE, bias: float = OPACITY_BIAS, hidden: int = 8):
        super().__init__()
        self.a = nn.Parameter(torch.tensor(float(slope)))
        self.b = nn.Parameter(torch.tensor(float(bias)))
        self.u = nn.Parameter(torch.linspace(1.0, 8.0, hidden))
        self.c = nn.Parameter(torch.linspace(-4.0, 0.0, hidden))
        self.w = nn.Parameter(torch.zeros(hidden))

    def forward(self, r: Tensor) -> Tensor:  # [N] -> [N] logits
        line = self.a.clamp_min(0.0) * r + self.b
        w = self.w.clamp_min(0.0)
        if not torch.is_grad_enabled() and not bool(w.any()):  # untrained: the bend is exactly zero
            return line
        return line + torch.tanh(self.u.clamp_min(0.0) * r[:, None] + self.c) @ w


def matrix_to_quaternion(R: Tensor) -> Tensor:  # [N, 3, 3] -> [N, 4] (w, x, y, z), w >= 0
    """Rotation matrices to unit quaternions (numerically stable branch per matrix)."""
    m = R
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + trace, m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], -1),
            torch.stack([m[:, 2, 1] - m[:, 1, 2], 1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0]], -1),
            torch.stack([m[:, 0, 2] - m[:, 2, 0], m[:, 0, 1] + m[:, 1, 0], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], m[:, 1, 2] + m[:, 2, 1]], -1),
            torch.stack([m[:, 1, 0] - m[:, 0, 1], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1], 1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]], -1),
        ],
        1,
    )  # [N, 4 candidates, 4]; candidate k has component k equal to 4 q_k^2, largest is most stable
    diag = torch.stack([trace, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    pick = diag.argmax(-1)
    q = cands[torch.arange(R.shape[0], device=R.device), pick]
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[:, :1] < 0, -q, q)


def support_unit(
    reliability: Tensor,  # [V] R_scene
    observations: Tensor,  # [V] observations folded into each voxel
) -> float:
    """The typical weight one observation adds to R_scene: the median over voxels of R_scene / count.

    Example:
        >>> support_unit(torch.tensor([0.5, 1.0, 3.0]), torch.tensor([1, 2, 3]))
        0.5
    """
    seen = observations > 0
    if not bool(seen.any()):
        return 1.0
    unit = float(torch.median(reliability[seen] / observations[seen].to(reliability.dtype)))
    return unit if unit > 1e-6 else 1e-6


class GaussianDecoder(nn.Module):
    """Decoder from fused scene fields to Gaussians (see module docstring for the equations).

    Args:
        feature_dim: L, channels of F_scene.
        min_thickness, min_extent, max_extent: clamps of the per-axis std in voxel units (smallest
            axis >= min_thickness, the other two >= min_extent, all <= max_extent).
    """

    def __init__(self, feature_dim: int, min_thickness: float = 0.05, min_extent: float = FULL_VOXEL_EXTENT,
                 max_extent: float = 1.0, opacity_slope: float = OPACITY_SLOPE, opacity_bias: float = OPACITY_BIAS,
                 free_space_slope: float = 4.0):
        super().__init__()
        self.feature_dim = feature_dim
        self.min_thickness, self.min_extent, self.max_extent = min_thickness, min_extent, max_extent
        self.opacity = MonotoneOpacity(opacity_slope, opacity_bias)
        self.free_space_penalty = MonotoneOpacity(free_space_slope, 0.0)
        self.offset = nn.Linear(feature_dim, 3)
        self.log_scale_delta = nn.Linear(feature_dim, 3)
        self.color_delta = nn.Linear(feature_dim, 3)
        for head in (self.offset, self.log_scale_delta, self.color_delta):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, fields: dict[str, Tensor], voxel_size: float, support_unit: float = 1.0) -> Gaussians:
        """Decode every voxel of ``fields`` (the dict returned by ``Scene.fields``); R_scene is
        counted in units of ``support_unit`` (see `support_unit`)."""
        opacities = self.opacities(fields["reliability"], fields.get("free_space"), support_unit)
        return Gaussians(opacities=opacities, **self.shapes_and_colours(fields, voxel_size))

    def opacities(
        self,
        support: Tensor,  # [N] R_scene
        free: Tensor | None,  # [N] free-space evidence, or None without it
        support_unit: float = 1.0,
    ) -> Tensor:  # [N] in (0, 1)
        """The opacity half of the decode: the only part that depends on the scene as a whole (its
        support unit), so `Scene.decode_from` recomputes it for every voxel and reuses the rest."""
        if not support_unit > 0:
            raise ValueError(f"support_unit: expected > 0, got {support_unit}")
        r = 1.0 - torch.exp(-support / support_unit)
        logit = self.opacity(r)
        if free is not None:
            logit = logit - self.free_space_penalty(free / (free + support).clamp_min(1e-12))
        return torch.sigmoid(logit)

    def base_shapes(self, fields: dict[str, Tensor], voxel_size: float) -> tuple[Tensor, Tensor, Tensor]:
        """What the heads on F_scene refine: the centroid [N, 3], the per-axis std in voxels from the
        second moments (footprint gain, clamps) [N, 3] and the axes' rotation as a quaternion
        [N, 4] (axis 0, the smallest, is the surface normal). `scene.shapes.voxel_shapes` is the
        fast path from the raw sums, held to this by the tests."""
        cov = fields["position_cov"] / (voxel_size * voxel_size)  # voxel units
        cov = 0.5 * (cov + cov.transpose(1, 2))
        # ascending: axis 0 is the surface normal (the numba path unless a gradient must reach the fields)
        eigh = symmetric_eigh3_reference if torch.is_grad_enabled() and cov.requires_grad else symmetric_eigh3
        eigval, eigvec = eigh(cov)
        std = eigval.clamp_min(0.0).sqrt().float() * FOOTPRINT_GAIN
        lo = torch.tensor([self.min_thickness, self.min_extent, self.min_extent], device=std.device)
        std = torch.minimum(torch.maximum(std, lo), torch.tensor(self.max_extent, device=std.device))
        rot = eigvec.float()
        rot = torch.where((torch.linalg.det(rot) < 0)[:, None, None], rot * torch.tensor([1.0, 1.0, -1.0], device=rot.device), rot)
        return fields["position_mean"], std, matrix_to_quaternion(rot)

    def heads_add_nothing(self) -> bool:
        """Whether the heads on F_scene are all zero (the training-free decoder's, as initialised) and
        no gradient is wanted: then they leave the base shapes and the fused colours as they are, and
        a decode skips them, and F_scene where the Gaussians do not carry it."""
        return not torch.is_grad_enabled() and not any(
            bool(p.any()) for head in (self.offset, self.log_scale_delta, self.color_delta) for p in head.parameters())

    def shapes_and_colours(self, fields: dict[str, Tensor], voxel_size: float,
                           base: tuple[Tensor, Tensor, Tensor] | None = None) -> dict[str, Tensor]:
        """Every Gaussian field but opacity (means, scales, quats, sh, features, labels), each a
        function of its own voxel's fields alone; ``base`` is `base_shapes` where the caller has it
        (then ``fields`` needs no positions). ``fields`` may lack F_scene when `heads_add_nothing`
        (then the Gaussians carry none)."""
        centroid, std, quats = self.base_shapes(fields, voxel_size) if base is None else base
        sh = fields["sh"] if "sh" in fields else rgb_to_sh_dc(fields["colour"])[:, None, :]
        if self.heads_add_nothing():  # the same values as below, whose heads add zeros, without their passes
            return {"means": centroid, "scales": voxel_size * std, "quats": quats, "sh": sh,
                    "features": fields.get("features"), "labels": fields.get("labels")}
        feats = fields["features"]
        means = centroid + voxel_size * self.offset(feats)
        scales = voxel_size * std * torch.exp(self.log_scale_delta(feats))
        sh = torch.cat([sh[:, :1] + self.color_delta(feats)[:, None] / SH_C0, sh[:, 1:]], 1)
        return {"means": means, "scales": scales, "quats": quats, "sh": sh, "features": feats,
                "labels": fields.get("labels")}
