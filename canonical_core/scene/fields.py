"""Scene fields from the per-voxel weighted sums: the one place sums become F_scene, colours, moments.

Both the streaming `Scene` and the batch reference `aggregate_batch` produce the same raw sums and
call `fields_from_sums`, so they can only differ in the sums themselves.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from ..gaussians.container import SH_C0
from ..config import KEY_BITS, KEY_OFFSET, SceneConfig
from .selection import scene_features
from .stored import SUMS, raw_sum, raw_sums, sh_bases, sum_rules

_SQ_INDEX = ((0, 1, 2), (1, 3, 4), (2, 4, 5))  # xx xy xz yy yz zz -> symmetric 3x3


def unpack_keys(keys: Tensor) -> Tensor:  # [V] int64 -> [V, 3] int64 voxel indices (i, j, k)
    mask = (1 << KEY_BITS) - 1
    return torch.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], -1) - KEY_OFFSET


def sh_sum_widths(degree: int) -> tuple[int, int]:
    """Columns of the SH normal-equation sums: (upper triangle of sum W b b^T without (0, 0), sum W b (c - 1/2) rows k >= 1)."""
    k = (degree + 1) ** 2
    return k * (k + 1) // 2 - 1, 3 * (k - 1)


def _check_sh_sums(r: Tensor, color_sum: Tensor, sh_a: Tensor, sh_b: Tensor) -> int:
    """K of the fit, after checking the sums' shapes against each other."""
    V = r.shape[0] if r.ndim == 1 else -1
    if V < 0 or tuple(color_sum.shape) != (V, 3) or sh_b.ndim != 2 or sh_b.shape[0] != V or sh_b.shape[1] % 3:
        raise ValueError(f"sh sums: expected r [V], color_sum [V, 3], sh_b [V, 3 (K - 1)], got r {list(r.shape)}, "
                         f"color_sum {list(color_sum.shape)}, sh_b {list(sh_b.shape)}")
    k = sh_b.shape[1] // 3 + 1
    if tuple(sh_a.shape) != (V, k * (k + 1) // 2 - 1):
        raise ValueError(f"sh_a: expected [{V}, {k * (k + 1) // 2 - 1}] for K = {k}, got {list(sh_a.shape)}")
    return k


def solve_sh_reference(
    r: Tensor,  # [V] R_scene (+ eps)
    color_sum: Tensor,  # [V, 3] sum W c (+ eps * representative colour)
    sh_a: Tensor,  # [V, K(K+1)/2 - 1]
    sh_b: Tensor,  # [V, 3 (K - 1)]
    regularization: float,
) -> Tensor:  # [V, K, 3]
    """Per-voxel least-squares SH colour fit from the streamed normal equations (pure PyTorch,
    differentiable; `solve_sh` is the fast path).

    Minimises sum W |c - 1/2 - sh^T b(d)|^2 + regularization * R_scene * |sh_{k>=1}|^2: a ridge that
    pulls the view-dependent terms toward zero (the DC colour) where few directions were seen.
    """
    k = _check_sh_sums(r, color_sum, sh_a, sh_b)
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


# A Cholesky pivot below this share of the matrix's largest diagonal entry is a direction the
# observations (and the ridge) leave undetermined: its coefficient is set to zero instead of
# amplifying round-off (only reachable with sh_regularization = 0).
_PIVOT_FLOOR = 1e-12


@numba.njit(cache=True, parallel=True)
def _solve_sh_kernel(
    r: np.ndarray,  # [V] float32 or float64
    color_sum: np.ndarray,  # [V, 3]
    sh_a: np.ndarray,  # [V, K(K+1)/2 - 1]
    sh_b: np.ndarray,  # [V, 3 (K - 1)]
    regularization: float,
    out: np.ndarray,  # [V, K, 3] float32, the solution
) -> None:
    k, V = out.shape[1], r.shape[0]
    chunk = 4096  # scratch matrices are allocated once per chunk of voxels, not per voxel
    for first in numba.prange((V + chunk - 1) // chunk):
        a = np.empty((k, k))
        b = np.empty((k, 3))
        inverse = np.empty(k)  # 1 / L_jj (0 for an undetermined direction): products, not divisions
        stop = min(V, (first + 1) * chunk)
        # the degrees in use get K as a constant (inlined), so their loops are unrolled; the same code
        if k == 4:
            for n in range(first * chunk, stop):
                _solve_sh_voxel(n, n, 4, r, color_sum, sh_a, sh_b, regularization, out, a, b, inverse)
        elif k == 1:
            for n in range(first * chunk, stop):
                _solve_sh_voxel(n, n, 1, r, color_sum, sh_a, sh_b, regularization, out, a, b, inverse)
        else:
            for n in range(first * chunk, stop):
                _solve_sh_voxel(n, n, k, r, color_sum, sh_a, sh_b, regularization, out, a, b, inverse)


@numba.njit(inline="always")
def _solve_sh_voxel(n, m, k, r, color_sum, sh_a, sh_b, regularization, out, a, b, inverse):
    """The K x K normal equations of row ``n`` of the sums, assembled into ``a``, ``b`` and solved
    into ``out[m]``."""
    rn = np.float64(r[n])
    column = 0
    for i in range(k):  # the upper triangle, row by row, as `sh_sum_widths` lays it out
        for j in range(i, k):
            if i == 0 and j == 0:
                a[0, 0] = SH_C0 * SH_C0 * rn
            else:
                a[i, j] = sh_a[n, column]
                column += 1
            a[j, i] = a[i, j]
        if i > 0:
            a[i, i] += regularization * rn
    for c in range(3):
        b[0, c] = SH_C0 * (color_sum[n, c] - 0.5 * rn)
    for i in range(1, k):
        for c in range(3):
            b[i, c] = sh_b[n, 3 * (i - 1) + c]
    scale = 0.0
    for i in range(k):
        scale = max(scale, abs(a[i, i]))
    floor = _PIVOT_FLOOR * scale
    # Cholesky A = L L^T in the lower triangle; an undetermined direction gets a zero column
    for j in range(k):
        d = a[j, j]
        for p in range(j):
            d -= a[j, p] * a[j, p]
        if d <= floor:
            for i in range(j, k):
                a[i, j] = 0.0
            inverse[j] = 0.0
            continue
        d = np.sqrt(d)
        a[j, j] = d
        inverse[j] = 1.0 / d
        for i in range(j + 1, k):
            s = a[i, j]
            for p in range(j):
                s -= a[i, p] * a[j, p]
            a[i, j] = s * inverse[j]
    for c in range(3):  # L y = b, then L^T x = y (zero pivots give zero components)
        for i in range(k):
            s = b[i, c]
            for p in range(i):
                s -= a[i, p] * b[p, c]
            b[i, c] = s * inverse[i]
        for i in range(k - 1, -1, -1):
            s = b[i, c]
            for p in range(i + 1, k):
                s -= a[p, i] * b[p, c]
            b[i, c] = s * inverse[i]
        for i in range(k):
            out[m, i, c] = b[i, c]


@numba.njit(cache=True, parallel=True)
def _solve_sh_stored_kernel(
    r_sum: np.ndarray,  # [V] float32 R_scene
    rep_rgb: np.ndarray,  # [V, 3] uint8, the representative's colour
    rgb: tuple,  # `stored.sum_rules` of rgb_mean, sh_a_central and sh_b_central
    sh_a: tuple,
    sh_b: tuple,
    eps: np.float32,  # `SceneConfig.research.eps`
    regularization: float,
    out: np.ndarray,  # [V, K, 3] float32, the solution
) -> None:
    k, V = out.shape[1], r_sum.shape[0]
    chunk = 4096  # scratch is allocated once per chunk of voxels, not per voxel
    for first in numba.prange((V + chunk - 1) // chunk):
        a = np.empty((k, k))
        b = np.empty((k, 3))
        inverse = np.empty(k)
        # one voxel's sums, made as `stored.raw_sums` and `fields_from_sums` make them (float32)
        r = np.empty(1, np.float32)
        color_sum = np.empty((1, 3), np.float32)
        sums_a = np.empty((1, sh_a[0].shape[1]), np.float32)
        sums_b = np.empty((1, sh_b[0].shape[1]), np.float32)
        stop = min(V, (first + 1) * chunk)
        for n in range(first * chunk, stop):
            rn = r_sum[n]
            for c in range(3):
                color_sum[0, c] = raw_sum(rgb, n, c, rn) + eps * (np.float32(rep_rgb[n, c]) / np.float32(255.0))
            for c in range(sums_a.shape[1]):
                sums_a[0, c] = raw_sum(sh_a, n, c, rn)
            for c in range(sums_b.shape[1]):
                sums_b[0, c] = raw_sum(sh_b, n, c, rn)
            r[0] = rn + eps
            if k == 4:  # the degrees in use get K as a constant, as in `_solve_sh_kernel`
                _solve_sh_voxel(0, n, 4, r, color_sum, sums_a, sums_b, regularization, out, a, b, inverse)
            elif k == 1:
                _solve_sh_voxel(0, n, 1, r, color_sum, sums_a, sums_b, regularization, out, a, b, inverse)
            else:
                _solve_sh_voxel(0, n, k, r, color_sum, sums_a, sums_b, regularization, out, a, b, inverse)


def solve_sh_stored(
    sums: dict[str, np.ndarray],  # a scene's stored sums (`Scene.sums`), [V, ...]: r_sum, rep_rgb and the colour's
    config: SceneConfig,
) -> Tensor:  # [V, K, 3] float32
    """`solve_sh` of the colour sums `fields_from_sums` makes (the same bits), solved per voxel from the
    stored float16 means and central moments as they are: each voxel's sums are made in the solve's
    own pass, never written out as [V, ...] float32 columns and read back."""
    r = np.ascontiguousarray(sums["r_sum"], np.float32)
    bases = sh_bases(sums["sh_a_central"].shape[1])
    out = np.empty((len(r), bases, 3), np.float32)
    if len(r):
        rules = [sum_rules(sums, name, bases) for name in ("rgb_mean", "sh_a_central", "sh_b_central")]
        _solve_sh_stored_kernel(r, sums["rep_rgb"], *rules, np.float32(config.research.eps),
                                float(config.decoder.sh_regularization), out)
    return torch.from_numpy(out)


def solve_sh(
    r: Tensor,  # [V] R_scene (+ eps)
    color_sum: Tensor,  # [V, 3] sum W c (+ eps * representative colour)
    sh_a: Tensor,  # [V, K(K+1)/2 - 1]
    sh_b: Tensor,  # [V, 3 (K - 1)]
    regularization: float,
) -> Tensor:  # [V, K, 3]
    """`solve_sh_reference`'s fit, solved per voxel by a Cholesky factorisation in a numba kernel
    (the batched LAPACK solve and the assembly of [V, K, K] matrices were a third of a decode).
    Falls back to the reference where a gradient must reach the sums.

    Example:
        >>> r = torch.tensor([2.0]); c = torch.tensor([[1.5, 1.0, 0.5]])   # two observations
        >>> sh = solve_sh(r, c, torch.zeros(1, 9), torch.zeros(1, 9), 0.003)
        >>> bool(torch.allclose(sh, solve_sh_reference(r, c, torch.zeros(1, 9), torch.zeros(1, 9), 0.003)))
        True
    """
    if torch.is_grad_enabled() and any(t.requires_grad for t in (r, color_sum, sh_a, sh_b)):
        return solve_sh_reference(r, color_sum, sh_a, sh_b, regularization)
    k = _check_sh_sums(r, color_sum, sh_a, sh_b)
    out = np.empty((r.shape[0], k, 3), np.float32)
    if r.shape[0]:
        # float32 or float64 sums as they come, strided or not (the kernel accumulates in float64 and
        # reads each voxel's sums once: a contiguous copy would cost more than it saves)
        sums = [t.detach().cpu().numpy() for t in (r, color_sum, sh_a, sh_b)]
        _solve_sh_kernel(*sums, float(regularization), out)
    return torch.from_numpy(out)


def sums_from_stored(t: dict[str, Tensor]) -> dict[str, Tensor]:
    """A scene's stored fields (`stored`: float16 means and central moments over R_scene, the
    representative's 8-bit direction) as float32 sums, as the fold kernel computes them
    (`stored.raw_sums`). Float32 sums (the batch reference's) pass unchanged."""
    stored = {k: v.numpy() for k, v in t.items() if k in SUMS or k in ("r_sum", "rep_dir")}
    out = {k: v for k, v in t.items() if k not in stored or k == "r_sum"}
    return out | {k: torch.from_numpy(v) for k, v in raw_sums(stored).items() if k != "r_sum"}


def _direction(x: Tensor) -> Tensor:  # [V, L] -> [V, L] unit length (0 for a zero vector)
    return x.float() / x.float().norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _labels(t: dict[str, Tensor]) -> Tensor:  # [V, S] label scores from their sums
    """The weighted mean of a voxel's label evidence; zeros where it has none (no labelled pixel)."""
    w = t["label_w"][:, None]
    return torch.where(w > 0, t["label_sum"] / torch.where(w > 0, w, 1.0), 0.0)


def fields_from_sums(sums: dict[str, np.ndarray | Tensor], config: SceneConfig, sort: bool = True) -> dict[str, Tensor]:
    """Scene fields from raw sums (rows are voxels; local positions in voxel units; a scene's stored
    means and central moments are made sums first, `sums_from_stored`).

    Returns a dict of tensors, one row per voxel (sorted by key when ``sort``):
        keys [V] int64, reliability [V] (R_scene = sum W), features [V, L] (F_scene =
        sum W F / (R_scene + eps)), representative_position [V, 3], representative_reliability [V],
        representative_feature [V, L] (its direction, unit length: only that enters the
        similarity weight), representative_colour [V, 3], colour [V, 3] (fused),
        position_mean [V, 3], position_cov [V, 3, 3] (world units), observations [V] int64,
        free_space [V] (see-through evidence, in R_scene's unit), sh [V, K, 3] (the solved SH colour
        fit, K = (sh_degree + 1)^2), and labels [V, S] when label scores were fused.
    Colour and position fall back smoothly to the representative's where R_scene ~ 0
    (``(sum W x + eps x_rep) / (R_scene + eps)``), so no voxel decodes to black or to the origin.
    A decode reads only some of them: `decoder_fields`.
    """
    voxel_size, eps = config.voxel_size, config.research.eps
    t = sums_from_stored({k: torch.as_tensor(v) for k, v in sums.items()})
    t["rep_rgb"] = t["rep_rgb"].float() / 255.0  # stored as the 8-bit input colour
    if sort:
        order = torch.argsort(t["keys"], stable=True)
        t = {k: v[order] for k, v in t.items()}
    r = t["r_sum"]
    den = (r + eps)[:, None]
    color_sum = t["rgb_sum"] + eps * t["rep_rgb"]
    centres = (unpack_keys(t["keys"]).to(torch.float64) + 0.5)
    local_rep = t["rep_pos"].double()  # the representative, in local voxel units
    mean_local = (t["pos_sum"].double() + eps * local_rep) / den.double()
    sq = t["pos_sq"].double()
    second = torch.stack([torch.stack([sq[:, j] for j in row], -1) for row in _SQ_INDEX], -2)
    second = (second + eps * local_rep[:, :, None] * local_rep[:, None, :]) / den.double()[:, :, None]
    cov_local = second - mean_local[:, :, None] * mean_local[:, None, :]
    out = {
        "keys": t["keys"],
        "reliability": r,
        "features": t["f_sum"] / den,
        "representative_position": ((centres + local_rep) * voxel_size).float(),
        "representative_reliability": t["rep_r"],
        "representative_feature": _direction(t["rep_f"]),
        "representative_colour": t["rep_rgb"],
        "colour": color_sum / den,
        "position_mean": ((centres + mean_local) * voxel_size).float(),
        "position_cov": (cov_local * voxel_size * voxel_size).float(),
        "observations": t["n_obs"].to(torch.int64),
        "free_space": t["free"],
        "sh": solve_sh(r + eps, color_sum, t["sh_a"], t["sh_b"], config.decoder.sh_regularization),
    }
    if t["label_sum"].shape[1] > 0:
        out["labels"] = _labels(t)
    return out


def decoder_fields(sums: dict[str, np.ndarray], config: SceneConfig, features: bool = True) -> dict[str, Tensor]:
    """The fields a decode reads besides the positions (`GaussianDecoder.shapes_and_colours`, its base
    shapes from `scene.shapes.voxel_shapes`), each the same as `fields_from_sums`'s, unsorted:
    features [V, L] (unless ``features`` is false), sh [V, K, 3], and labels [V, S] when label scores
    were fused. From a scene's
    stored sums (`Scene.sums`: F_scene from its stored mean in one pass, `selection.scene_features`;
    the SH fit from the stored moments in another, `solve_sh_stored`), without the fields no decode
    reads (the representative's, the fused colour, the counts), each a pass over every voxel that
    decodes."""
    eps, rows = config.research.eps, np.arange(len(sums["r_sum"]))
    out = {"sh": solve_sh_stored(sums, config)} | ({"features": scene_features(sums, rows, eps)} if features else {})
    if "label_mean" in sums:  # stored only with label channels (without them, label_sum is [V, 0])
        t = {k: torch.as_tensor(v) for k, v in raw_sums({k: sums[k] for k in ("r_sum", "label_mean", "label_w")}).items()}
        out["labels"] = _labels(t)
    return out
