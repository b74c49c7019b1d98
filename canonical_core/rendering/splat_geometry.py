"""The image model's constants and its EWA splat arithmetic, written once for both CPU backends.

The image model (3DGS, Kerbl et al. 2023), with pixel (u, v) centred at (u, v):
- EWA splatting: Sigma = R S S^T R^T, Sigma_2D = J W Sigma W^T J^T + 0.3 I (the low-pass floor).
  J is evaluated at the mean with x/z and y/z clamped to the image plus 15 % of its width/height
  on each side (3DGS's 1.3 tan(fov / 2)), so Gaussians far off-screen keep a bounded footprint.
- A splat contributes alpha = min(0.99, opacity * exp(-q / 2)), q = d^T Sigma_2D^-1 d, at pixels
  with q <= 9 (its 3-sigma ellipse) and alpha >= 1/255. Truncating at the ellipse rather than at
  tile-quantised bounding squares (as 3DGS does) keeps the image independent of the tiling.
- Front-to-back compositing in order of view-space depth (ties: input order); a pixel stops
  before the splat that would take its transmittance below 1e-4.
Culling: means closer than the near plane (as in 3DGS); besides that only what cannot contribute:
opacity below 1/255, non-finite geometry (overflow), and support boxes that miss the image.

`camera_point` and `screen_geometry` use arithmetic operators only, so the same source runs on
torch tensors (the reference, with autograd) and, compiled by numba, on float32 scalars (the fast
path), and both give bitwise-identical splats. That is why they avoid literals (numba would
promote float32 to float64) and scalar / tensor (torch computes it as a reciprocal times).
"""

from __future__ import annotations

import math

import numba
import numpy as np

TILE_SIZE = 16
LOW_PASS = 0.3  # px^2 added to the diagonal of every 2D covariance
MAX_ALPHA = 0.99
MIN_ALPHA = 1.0 / 255.0
MIN_TRANSMITTANCE = 1e-4
SUPPORT_SIGMAS = 3.0
JACOBIAN_CLAMP_MARGIN = 0.15  # fraction of the image size allowed beyond each edge in J
# The fast path skips pixels outside a splat's box, so the box must not be tight to rounding.
BOX_PADDING = 1e-3  # px
MIN_QUAT_NORM2 = 1e-24  # a zero quaternion then means a zero rotation: the splat is a point


def camera_point(mx, my, mz, view):
    """World -> camera coordinates; ``view`` holds the 12 entries of w2c[:3] row by row."""
    x = view[0] * mx + view[1] * my + view[2] * mz + view[3]
    y = view[4] * mx + view[5] * my + view[6] * mz + view[7]
    z = view[8] * mx + view[9] * my + view[10] * mz + view[11]
    return x, y, z


def screen_geometry(x, y, z, u_slope, v_slope, qw, qx, qy, qz, quat_norm2, sx, sy, sz, view, fx, fy, cx, cy, low_pass):
    """Pixel centre, conic (a, b, c) of Sigma_2D^-1 and the variances of Sigma_2D of one splat.

    (x, y, z): the mean in camera coordinates; u_slope, v_slope: x/z and y/z clamped for J;
    (qw, qx, qy, qz): a quaternion, any length; quat_norm2: its squared length, clamped above 0;
    (sx, sy, sz): scales.
    """
    ww, xx, yy, zz = qw * qw, qx * qx, qy * qy, qz * qz
    xy, xz, yz, wx, wy, wz = qx * qy, qx * qz, qy * qz, qw * qx, qw * qy, qw * qz
    # |q|^2 R, with 1 - 2 (y^2 + z^2) written as w^2 + x^2 - y^2 - z^2 (no literals); the 1 / |q|^2
    # goes into the scales. No square root: torch's is not correctly rounded, numba's is.
    r00, r01, r02 = (ww + xx) - (yy + zz), (xy - wz) + (xy - wz), (xz + wy) + (xz + wy)
    r10, r11, r12 = (xy + wz) + (xy + wz), (ww + yy) - (xx + zz), (yz - wx) + (yz - wx)
    r20, r21, r22 = (xz - wy) + (xz - wy), (yz + wx) + (yz + wx), (ww + zz) - (xx + yy)
    # Rows of J W: the perspective Jacobian at the mean times the view rotation.
    ju0 = (fx * (view[0] - u_slope * view[8])) / z
    ju1 = (fx * (view[1] - u_slope * view[9])) / z
    ju2 = (fx * (view[2] - u_slope * view[10])) / z
    jv0 = (fy * (view[4] - v_slope * view[8])) / z
    jv1 = (fy * (view[5] - v_slope * view[9])) / z
    jv2 = (fy * (view[6] - v_slope * view[10])) / z
    # F = J W R S (2 x 3), so that Sigma_2D = F F^T + low_pass I.
    sx, sy, sz = sx / quat_norm2, sy / quat_norm2, sz / quat_norm2
    fu0 = (ju0 * r00 + ju1 * r10 + ju2 * r20) * sx
    fu1 = (ju0 * r01 + ju1 * r11 + ju2 * r21) * sy
    fu2 = (ju0 * r02 + ju1 * r12 + ju2 * r22) * sz
    fv0 = (jv0 * r00 + jv1 * r10 + jv2 * r20) * sx
    fv1 = (jv0 * r01 + jv1 * r11 + jv2 * r21) * sy
    fv2 = (jv0 * r02 + jv1 * r12 + jv2 * r22) * sz
    var_u = fu0 * fu0 + fu1 * fu1 + fu2 * fu2
    cov_uv = fu0 * fv0 + fu1 * fv1 + fu2 * fv2
    var_v = fv0 * fv0 + fv1 * fv1 + fv2 * fv2
    # det(F F^T) as the sum of squared 2x2 minors of F (Cauchy-Binet): never negative, unlike
    # var_u * var_v - cov_uv^2, which cancels catastrophically for needle-like splats.
    m01, m02, m12 = fu0 * fv1 - fu1 * fv0, fu0 * fv2 - fu2 * fv0, fu1 * fv2 - fu2 * fv1
    det = m01 * m01 + m02 * m02 + m12 * m12 + low_pass * (var_u + var_v + low_pass)
    var_u = var_u + low_pass
    var_v = var_v + low_pass
    u = (fx * x) / z + cx
    v = (fy * y) / z + cy
    return u, v, var_v / det, -cov_uv / det, var_u / det, var_u, var_v


def slope_bounds(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> tuple[float, ...]:
    """Clamp range of x/z and y/z for the Jacobian: the image plus the margin on each side."""
    margin_u = JACOBIAN_CLAMP_MARGIN * width / fx
    margin_v = JACOBIAN_CLAMP_MARGIN * height / fy
    return (
        (-0.5 - cx) / fx - margin_u,
        (width - 0.5 - cx) / fx + margin_u,
        (-0.5 - cy) / fy - margin_v,
        (height - 0.5 - cy) / fy + margin_v,
    )


_camera_point = numba.njit(camera_point)
_screen_geometry = numba.njit(screen_geometry)


# Columns of the fast path's packed splat records (one or two cache lines per splat in the
# tile loop): pixel centre, conic, view depth, opacity, and the q beyond which alpha < 1/255.
U, V, CONIC_A, CONIC_B, CONIC_C, DEPTH, OPACITY, SUPPORT = range(8)
SPLAT_RECORD = 8


@numba.njit(parallel=True, cache=True)
def project_numba(
    means: np.ndarray,  # [N, 3] float32
    quats: np.ndarray,  # [N, 4] float32
    scales: np.ndarray,  # [N, 3] float32
    opacities: np.ndarray,  # [N] float32
    view: tuple,  # 12 float32: w2c[:3] row by row
    intrinsics: tuple,  # float32 fx, fy, cx, cy
    slopes: tuple,  # float32 u_min, u_max, v_min, v_max (see slope_bounds)
    near_plane: float,
    width: int,
    height: int,
    out_splats: np.ndarray,  # [N, SPLAT_RECORD] float32 records (columns above), zero where culled
    out_boxes: np.ndarray,  # [N, 4] int32 pixel box u_lo, u_hi, v_lo, v_hi; empty (lo > hi) if culled
) -> None:
    fx, fy, cx, cy = intrinsics
    low_pass = np.float32(LOW_PASS)
    for i in numba.prange(means.shape[0]):
        out_boxes[i, 0], out_boxes[i, 1], out_boxes[i, 2], out_boxes[i, 3] = 0, -1, 0, -1
        out_splats[i, :] = 0  # culled: a zero record (the caller's arrays need not be zeroed)
        x, y, z = _camera_point(means[i, 0], means[i, 1], means[i, 2], view)
        opacity = opacities[i]
        if not (z >= near_plane and opacity >= np.float32(MIN_ALPHA)):
            continue
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        quat_norm2 = max(qw * qw + qx * qx + qy * qy + qz * qz, np.float32(MIN_QUAT_NORM2))
        u_slope = min(max(x / z, slopes[0]), slopes[1])
        v_slope = min(max(y / z, slopes[2]), slopes[3])
        u, v, a, b, c, var_u, var_v = _screen_geometry(
            x, y, z, u_slope, v_slope, qw, qx, qy, qz, quat_norm2,
            scales[i, 0], scales[i, 1], scales[i, 2], view, fx, fy, cx, cy, low_pass,
        )  # fmt: skip
        # Overflow (enormous scales) shows up as inf/NaN: such a splat cannot be drawn.
        finite = math.isfinite(u) and math.isfinite(v) and math.isfinite(var_u) and math.isfinite(var_v)
        if not (finite and math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
            continue
        # The same box rule as projection.pixel_boxes, so both backends bin into the same tiles.
        # Above 255 opacity = 90.02 (> e^4.5 by more than the log's rounding) the support is 9
        # whatever the log gives, so the log (a sixth of this kernel's time) is skipped there.
        scaled = 255.0 * opacity
        support_q = SUPPORT_SIGMAS**2 if scaled >= 90.02 else min(SUPPORT_SIGMAS**2, max(0.0, 2.0 * math.log(scaled)))
        half_u = math.sqrt(support_q * var_u) + BOX_PADDING
        half_v = math.sqrt(support_q * var_v) + BOX_PADDING
        u_lo, u_hi = max(math.ceil(u - half_u), 0.0), min(math.floor(u + half_u), width - 1.0)
        v_lo, v_hi = max(math.ceil(v - half_v), 0.0), min(math.floor(v + half_v), height - 1.0)
        if u_lo > u_hi or v_lo > v_hi:
            continue
        record = out_splats[i]
        record[U], record[V], record[DEPTH], record[OPACITY] = u, v, z, opacity
        record[CONIC_A], record[CONIC_B], record[CONIC_C] = a, b, c
        # With a margin for rounding, so that skipping q > support leaves the image unchanged; it
        # is 9 exactly for opacities above 0.35, where the q <= 9 test itself decides.
        record[SUPPORT] = min(np.float32(SUPPORT_SIGMAS**2), np.float32(support_q + 1e-4))
        out_boxes[i, 0], out_boxes[i, 1] = int(u_lo), int(u_hi)
        out_boxes[i, 2], out_boxes[i, 3] = int(v_lo), int(v_hi)
