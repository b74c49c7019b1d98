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


# Inlined into the projection's loop, and IEEE division without Python's zero check, so that the
# loop compiles to vector code; Gaussians that divide by zero are culled by the caller.
_camera_point = numba.njit(camera_point, error_model="numpy", inline="always")
_screen_geometry = numba.njit(screen_geometry, error_model="numpy", inline="always")


# Columns of the fast path's packed splat records (one or two cache lines per splat in the
# tile loop): pixel centre, conic, view depth, opacity, and the q beyond which alpha < 1/255.
U, V, CONIC_A, CONIC_B, CONIC_C, DEPTH, OPACITY, SUPPORT = range(8)
SPLAT_RECORD = 8


PROJECTION_CHUNK = 512  # Gaussians per parallel task of `project_numba` (its scratch stays in cache)
# That scratch: a row of PROJECTION_CHUNK floats per quantity, starting at these offsets: the splat
# (u, v, conic a, b, c, depth, var_u, var_v), whether it is drawn (1 or 0), and its box for a
# support of 9 (u_lo, u_hi, v_lo, v_hi); constants, so the compiler knows the rows do not overlap.
_U, _V, _A, _B, _C, _Z, _VAR_U, _VAR_V, _DRAWN, _U_LO, _U_HI, _V_LO, _V_HI, _SCRATCH = (
    k * PROJECTION_CHUNK for k in range(14))


@numba.njit(parallel=True, cache=True, error_model="numpy")
def project_numba(
    means: np.ndarray,  # [N, 3] float32, C-contiguous
    quats: np.ndarray,  # [N, 4] float32, C-contiguous
    scales: np.ndarray,  # [N, 3] float32, C-contiguous
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
    low_pass, nine, zero, one = np.float32(LOW_PASS), SUPPORT_SIGMAS**2, np.float32(0.0), np.float32(1.0)
    # Flat views indexed 3 i + k, and the scratch rows at constant offsets: strides and offsets the
    # compiler knows, so that the first loop below compiles to vector code.
    m, q, s = means.reshape(-1), quats.reshape(-1), scales.reshape(-1)
    n = opacities.shape[0]
    for chunk in numba.prange((n + PROJECTION_CHUNK - 1) // PROJECTION_CHUNK):
        first, count = chunk * PROJECTION_CHUNK, min(PROJECTION_CHUNK, n - chunk * PROJECTION_CHUNK)
        f = np.empty(_SCRATCH, np.float32)
        # 1) Every Gaussian's splat, and its box for the support of opacities above 0.35, with no
        # branch: the culled are computed too, and flagged. Culled: behind the near plane, too
        # transparent, or overflowing (enormous scales show up as inf/NaN; x * 0 is 0 only for a
        # finite x).
        for j in range(count):
            i = first + j
            x, y, z = _camera_point(m[3 * i], m[3 * i + 1], m[3 * i + 2], view)
            qw, qx, qy, qz = q[4 * i], q[4 * i + 1], q[4 * i + 2], q[4 * i + 3]
            quat_norm2 = max(qw * qw + qx * qx + qy * qy + qz * qz, np.float32(MIN_QUAT_NORM2))
            u_slope = min(max(x / z, slopes[0]), slopes[1])
            v_slope = min(max(y / z, slopes[2]), slopes[3])
            u, v, a, b, c, var_u, var_v = _screen_geometry(
                x, y, z, u_slope, v_slope, qw, qx, qy, qz, quat_norm2,
                s[3 * i], s[3 * i + 1], s[3 * i + 2], view, fx, fy, cx, cy, low_pass,
            )  # fmt: skip
            finite = (u * zero + v * zero + var_u * zero + var_v * zero + a * zero + b * zero + c * zero) == zero
            drawn = (z >= near_plane) & (opacities[i] >= np.float32(MIN_ALPHA)) & finite
            u_lo, u_hi, v_lo, v_hi = _pixel_box(u, v, var_u, var_v, nine, width, height)
            f[_U + j], f[_V + j], f[_Z + j] = u, v, z
            f[_A + j], f[_B + j], f[_C + j] = a, b, c
            f[_VAR_U + j], f[_VAR_V + j], f[_DRAWN + j] = var_u, var_v, one if drawn else zero
            # bounds within the image are integers below 2^24: exact in float32
            f[_U_LO + j], f[_U_HI + j], f[_V_LO + j], f[_V_HI + j] = u_lo, u_hi, v_lo, v_hi
        # 2) Into the records, one Gaussian at a time (a function of its own: in this loop's body it
        # kept the first loop from being vectorised).
        _write_records(f, first, count, opacities, width, height, out_splats, out_boxes)


@numba.njit(cache=True)
def _write_records(f, first, count, opacities, width, height, out_splats, out_boxes):
    """Step 2 of `project_numba`: Gaussians [first, first + count) from the chunk's scratch ``f``
    into the records and boxes. Those whose opacity gives a support below 9 get their box again:
    the same box rule as projection.pixel_boxes, so both backends bin into the same tiles. Above
    255 opacity = 90.02 (> e^4.5 by more than the log's rounding) the support is 9 whatever the
    log gives."""
    nine, zero = SUPPORT_SIGMAS**2, np.float32(0.0)
    for j in range(count):
        i = first + j
        drawn = f[_DRAWN + j] != zero
        support_q, scaled = nine, 255.0 * opacities[i]
        u_lo, u_hi, v_lo, v_hi = f[_U_LO + j], f[_U_HI + j], f[_V_LO + j], f[_V_HI + j]
        if drawn and scaled < 90.02:
            support_q = min(nine, max(0.0, 2.0 * math.log(scaled)))
            u_lo, u_hi, v_lo, v_hi = _pixel_box(f[_U + j], f[_V + j], f[_VAR_U + j],
                                                f[_VAR_V + j], support_q, width, height)  # fmt: skip
        record = out_splats[i]
        if not drawn or u_lo > u_hi or v_lo > v_hi:
            record[:] = zero
            out_boxes[i, 0], out_boxes[i, 1], out_boxes[i, 2], out_boxes[i, 3] = 0, -1, 0, -1
            continue
        record[U], record[V], record[DEPTH], record[OPACITY] = f[_U + j], f[_V + j], f[_Z + j], opacities[i]
        record[CONIC_A], record[CONIC_B], record[CONIC_C] = f[_A + j], f[_B + j], f[_C + j]
        # With a margin for rounding, so that skipping q > support leaves the image unchanged;
        # it is 9 exactly for opacities above 0.35, where the q <= 9 test itself decides.
        record[SUPPORT] = min(np.float32(nine), np.float32(support_q + 1e-4))
        out_boxes[i, 0], out_boxes[i, 1] = int(u_lo), int(u_hi)
        out_boxes[i, 2], out_boxes[i, 3] = int(v_lo), int(v_hi)


@numba.njit(inline="always")
def _pixel_box(u, v, var_u, var_v, support_q, width, height):
    """Pixel centres that can receive a splat (float64 bounds, lo > hi where none): q <= support_q, padded."""
    half_u = math.sqrt(support_q * var_u) + BOX_PADDING
    half_v = math.sqrt(support_q * var_v) + BOX_PADDING
    u_lo, u_hi = max(np.ceil(u - half_u), 0.0), min(np.floor(u + half_u), width - 1.0)
    v_lo, v_hi = max(np.ceil(v - half_v), 0.0), min(np.floor(v + half_v), height - 1.0)
    return u_lo, u_hi, v_lo, v_hi
