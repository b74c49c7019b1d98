"""``solve_colours``: render-consistent colours, solved against the views the scene was fused from.

The analytic decoder gives each Gaussian its voxel's fused colour, a weighted mean of the pixels
that landed in the voxel. But a rendered pixel blends several overlapping Gaussians, so even a
view the scene was fused from does not get its own colours back. With geometry and opacity fixed a
render is linear in the SH coefficients,
colour_v(p) = sum_i w_i(p) sum_k Y_k(d_vi) sh_ik + 0.5 (`rendering.weights.blend_weight_rows`,
d_vi the direction from view v's centre to Gaussian i), so the coefficients that make the renders
reproduce the input views are a linear least-squares problem. This solves it for offsets x_ik to
the coefficients up to ``degree`` (1: DC and the three linear terms, so the fit can tell a colour
that changes across the views from one that does not):

    min_x  sum_v sum_p |sum_i w_i(p) sum_k Y_k(d_vi) x_ik - (I_v(p) - render_v(p))|^2
           + sum_ik (ridge * e_ik + prior * peak_k^2) |x_ik|^2,   e_ik = sum_v Y_k(d_vi)^2 sum_p w_i(p)^2

by conjugate gradients, preconditioned with each Gaussian's own K x K block of the system (the clamp
max(0, .) of the SH colour is left out).
That is the fit for ``colour="composited"`` renders. Views are shown in ``"normalised"`` colour by
default (`rendering.render`: the blend over its weight alpha(p) = sum_i w_i(p)), which is as linear
in the coefficients, so the default fit divides each pixel's weights by its alpha and fits only
the pixels the scene covers (alpha >= 1/2, the evaluation's covered): with composited rows a partly
covered pixel asks for brighter colours to make up for the black behind it, which a normalised
render then shows too bright.
The system keeps the weights of at least `ROW_MIN_WEIGHT` (the tails behind a surface and at the
rims of splats are most of the weights and little of any pixel's colour), each row scaled to keep
its pixel's whole weight, while b is taken against the whole render: a scene that already shows its
views is left as it is.
``ridge`` shrinks every offset relative to its own evidence e_ik; ``prior`` keeps the fused colour
of Gaussians the views barely see (hidden, or at the edge of the images), which the fit cannot
determine; peak_k, the largest |Y_k| (SH_C0, SH_C1), counts it in colour units. A Gaussian seen
from one direction only cannot tell DC from linear terms: the prior splits its offset between them
in proportion, which agrees with that one view and changes little elsewhere. Training-free: no
learned weights, the same answer for the same scene and views on any number of threads.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from typing import Callable, Sequence, get_args

import numba
import numpy as np
import torch
from torch import Tensor

from ..frame import Frame
from ..gaussians import Gaussians
from ..gaussians.container import GEOMETRY, SH_C0, check_finite
from ..rendering import Colour
from ..rendering.renderer import blend_rgb
from ..rendering.sh import SH_C1, sh_basis_at_points
from ..rendering.weights import WeightsBackend, weight_rows_and_blend

# accumulated alpha at or above which a pixel counts as covered: the pixels the solve fits in normalised
# colour, and the evaluation's "covered" pixels (`eval.metrics`), so the two agree
COVERED_ALPHA = 0.5
# the least compositing weight the system keeps: a splat that adds less than 1 % to a pixel carries
# little of its colour, but such tails (splats far behind the surface, the rims of splats) are more
# than half of all weights, and the solve's time is a pass over the weights per step
ROW_MIN_WEIGHT = 0.01


class SolveStopped(Exception):
    """Raised by `colour_offsets` when its ``stop`` says so: the caller wants the CPU back (a
    service's background solve gives way to a frame that arrives)."""


def _check(views: Sequence[Frame], ridge: float, prior: float, iterations: int, degree: int, colour: str) -> None:
    if isinstance(views, Frame) or not isinstance(views, Sequence) or not views:
        raise ValueError("views: expected a non-empty sequence of Frames")
    for i, view in enumerate(views):
        if not isinstance(view, Frame):
            raise ValueError(f"views[{i}]: expected a Frame, got {type(view).__name__}")
    def number(value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    if not (number(ridge) and ridge >= 0):
        raise ValueError(f"ridge: expected a non-negative weight, got {ridge!r}")
    if not (number(prior) and prior > 0):
        raise ValueError(f"prior: expected a positive weight, got {prior!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations: expected a positive integer, got {iterations!r}")
    if isinstance(degree, bool) or not isinstance(degree, int) or degree not in (0, 1):
        raise ValueError(f"degree: expected 0 (DC only) or 1, got {degree!r}")
    if colour not in get_args(Colour):
        raise ValueError(f"colour: expected one of {list(get_args(Colour))}, got {colour!r}")


# The transposed products scatter into Gaussians that many rows share: each view of a group sums
# into its own buffer, then the group is contracted with the basis. A fixed group size bounds the
# buffers (GROUP x N x channels) and keeps the result independent of the machine's thread count.
VIEW_GROUP = 8


@numba.njit(parallel=True, cache=True)
def _contract_group(
    out: np.ndarray,  # [N, K, 3] float32, added to
    partial: np.ndarray,  # [GROUP, N, 3] float32: each view's sums in colour space
    bases: np.ndarray,  # [V, N, K] float32
    first: int,  # the group's first view
    group: int,  # views in the group
) -> None:
    """out_ik += sum over the group's views g of Y_k(d_gi) partial_gi (colour space to coefficients),
    in a fixed view order, so the sum does not depend on the thread count."""
    for i in numba.prange(out.shape[0]):
        for g in range(group):
            for k in range(out.shape[1]):
                bk = bases[first + g, i, k]
                out[i, k, 0] += bk * partial[g, i, 0]
                out[i, k, 1] += bk * partial[g, i, 1]
                out[i, k, 2] += bk * partial[g, i, 2]


@numba.njit(parallel=True, cache=True)
def _contract_blocks(
    out: np.ndarray,  # [N, K, K] float32, added to
    partial: np.ndarray,  # [GROUP, N] float32: each view's sum of squared weights of each Gaussian
    bases: np.ndarray,  # [V, N, K] float32
    first: int,  # the group's first view
    group: int,  # views in the group
) -> None:
    """out_ikl += sum over the group's views g of Y_k(d_gi) Y_l(d_gi) partial_gi: each Gaussian's own
    block of A^T A, in a fixed view order."""
    for i in numba.prange(out.shape[0]):
        for g in range(group):
            for k in range(out.shape[1]):
                bk = bases[first + g, i, k] * partial[g, i]
                for m in range(out.shape[2]):
                    out[i, k, m] += bk * bases[first + g, i, m]


@numba.njit(parallel=True, cache=True)
def _sh_products(
    starts: np.ndarray,  # [R + 1] int32 CSR row starts (rows view-major)
    columns: np.ndarray,  # [E] int32
    values: np.ndarray,  # [E] float32
    view_rows: np.ndarray,  # [V + 1] int64 where each view's rows start
    bases: np.ndarray,  # [V, N, K] float32 Y_k of each Gaussian seen from each view, K = 1 or 4
    x: np.ndarray,  # [N, K, 3] float32 coefficient offsets, or [0, K, 3]: none (zero)
    y: np.ndarray,  # [R, 3] float32 per-pixel colours, or [0, 3]: none (zero)
    blocks: bool,  # also sum each Gaussian's block of A^T A, sum_v Y_k(d_vi) Y_l(d_vi) sum_p w_i(p)^2
) -> tuple[np.ndarray, np.ndarray]:  # A^T (A x - y) [N, K, 3] float32; blocks [N, K, K] ([0, K, K] unless asked)
    """A^T (A x - y) in one pass over the weights: each pixel's colour change (a float64 sum, as a
    render) is scattered back through the same row while it is in cache, instead of streaming the
    weights once for A x and again for A^T (a conjugate-gradient step is one such product, with
    no y). The solve's first pass asks for its right-hand side, the warm start's residual and the
    blocks (their diagonal is the evidence e_ik) together. Grouped by views, so the result does not
    depend on the thread count."""
    n, num_bases = bases.shape[1], bases.shape[2]
    with_x, with_y = x.shape[0] > 0, y.shape[0] > 0
    out = np.zeros((n, num_bases, 3), np.float32)
    own = np.zeros((n if blocks else 0, num_bases, num_bases), np.float32)
    partial = np.empty((VIEW_GROUP, n, 3), np.float32)
    partial_squares = np.empty((VIEW_GROUP, n if blocks else 0), np.float32)
    seen = np.empty((VIEW_GROUP, n if with_x else 0, 3), np.float32)
    for first in range(0, view_rows.shape[0] - 1, VIEW_GROUP):
        group = min(VIEW_GROUP, view_rows.shape[0] - 1 - first)
        for g in numba.prange(group):
            v = first + g
            partial[g] = 0.0
            if blocks:
                partial_squares[g] = 0.0
            if with_x:
                for i in range(n):  # the colour offsets as view v sees them, sum_k Y_k x_k
                    for c in range(3):
                        s = np.float32(0.0)
                        for k in range(num_bases):
                            s += bases[v, i, k] * x[i, k, c]
                        seen[g, i, c] = s
            for r in range(view_rows[v], view_rows[v + 1]):
                s0 = s1 = s2 = 0.0
                if with_x:
                    for e in range(starts[r], starts[r + 1]):
                        i, w = columns[e], np.float64(values[e])
                        s0 += w * seen[g, i, 0]
                        s1 += w * seen[g, i, 1]
                        s2 += w * seen[g, i, 2]
                if with_y:
                    s0 -= y[r, 0]
                    s1 -= y[r, 1]
                    s2 -= y[r, 2]
                y0, y1, y2 = np.float32(s0), np.float32(s1), np.float32(s2)
                for e in range(starts[r], starts[r + 1]):
                    i, w = columns[e], values[e]
                    partial[g, i, 0] += w * y0
                    partial[g, i, 1] += w * y1
                    partial[g, i, 2] += w * y2
                    if blocks:
                        partial_squares[g, i] += w * w
        _contract_group(out, partial, bases, first, group)
        if blocks:
            _contract_blocks(own, partial_squares, bases, first, group)
    return out, own


def _row_scale(
    starts: np.ndarray,  # [R + 1] int32 CSR row starts
    values: np.ndarray,  # [E] float32
    alpha: np.ndarray,  # [R] float32 each row's whole alpha
) -> np.ndarray:  # [E] float32: each entry's row's alpha over the row's sum
    """The factor that makes each row of kept weights sum to the pixel's whole alpha: the weight of
    the dropped tail, shared in proportion, so that a change of colour the views show in full is
    asked of the kept Gaussians in full."""
    counts = np.diff(starts)
    rows = np.repeat(np.arange(len(counts)), counts)
    sums = np.bincount(rows, weights=values, minlength=len(counts))
    factor = np.divide(alpha, sums, out=np.ones(len(counts)), where=sums > 0)
    return factor[rows].astype(np.float32)


def _arrays(A: Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # CSR row starts, columns, values
    return A.crow_indices().numpy(), A.col_indices().numpy(), A.values().numpy()


def _stop_if(stop: Callable[[], bool] | None) -> None:
    if stop is not None and stop():
        raise SolveStopped("the colour solve was stopped by its caller")


def colour_system(
    gaussians: Gaussians,
    views: Sequence[Frame],
    backend: WeightsBackend = "cpu",
    colour: Colour = "normalised",
    stop: Callable[[], bool] | None = None,
) -> tuple[Tensor, Tensor]:  # A: sparse CSR [P, N] (int32 indices), residual b [P, 3]
    """The linear system of the fit: A's rows are the views' pixels (view-major), its columns the
    Gaussians, its entries the compositing weights of at least `ROW_MIN_WEIGHT`, each row scaled to
    its pixel's whole weight (``"normalised"``: to 1, over the kept weights' sum, and no row for a
    pixel they cover less than `COVERED_ALPHA`; ``"composited"``: to the render's alpha, the dropped
    tail's weight shared in proportion); b is each pixel's colour minus its render in that mode
    (`rendering.render`, every weight in), 0 for a pixel without a row. ``stop`` is asked before
    each view (`SolveStopped`)."""
    starts, columns, weights, residuals = [np.zeros(1, np.int64)], [], [], []
    for view in views:
        _stop_if(stop)
        camera = view.camera
        # the residual against the render itself, every weight in, from the rows' own compositor
        # pass: a scene that already shows its views is left as it is, whatever the rows leave out
        (s, c, v, scale), blend = weight_rows_and_blend(
            gaussians, camera, COVERED_ALPHA if colour == "normalised" else None, backend, min_weight=ROW_MIN_WEIGHT)
        residual = view.rgb.reshape(-1, 3).float() / 255.0 - blend_rgb(blend, colour).reshape(-1, 3).float()
        if colour == "composited":  # each row scaled to the render's alpha, as a normalised row sums to 1
            v = v * _row_scale(s, v, (1.0 - blend.transmittance).reshape(-1).numpy())
        if colour == "normalised":
            residual[torch.from_numpy(scale == 0)] = 0.0
        residuals.append(residual)
        starts.append(s[1:] + starts[-1][-1])
        columns.append(c)
        weights.append(v)
    starts = np.concatenate(starts)
    if starts[-1] >= 2**31:
        raise ValueError(f"views: {starts[-1]} compositing weights in all, more than int32 indices hold; keep fewer or smaller views")
    with warnings.catch_warnings():  # torch flags sparse CSR as beta; it is only the container here
        warnings.simplefilter("ignore", UserWarning)
        A = torch.sparse_csr_tensor(torch.from_numpy(starts.astype(np.int32)), torch.from_numpy(np.concatenate(columns)),
                                    torch.from_numpy(np.concatenate(weights)), (len(starts) - 1, len(gaussians)))
    return A, torch.cat(residuals)


def colour_offsets(
    gaussians: Gaussians,
    views: Sequence[Frame],  # the frames the scene was fused from: rgb and camera are used
    initial: Tensor | None = None,  # [N, K, 3] float32 offsets to start from (a warm start); None: zeros
    ridge: float = 0.3,
    prior: float = 1.0,
    iterations: int = 4,
    degree: int = 1,
    backend: WeightsBackend = "cpu",
    colour: Colour = "normalised",
    stop: Callable[[], bool] | None = None,
) -> Tensor:  # [N, K, 3] float32 offsets x_ik, K = (min(degree, sh_degree) + 1)^2
    """The offsets of `solve_colours` (module docstring), by ``iterations`` steps of conjugate
    gradients from ``initial``. A solution of a scene that has changed little since is a good
    start: a few steps from it come close to a full solve from zero (a streaming scene re-solves so).
    ``stop``, if given, is asked between the solve's steps (each view of the system, each
    iteration): when it answers True the solve gives up at once.

    Raises:
        ValueError: as `solve_colours`, and an ``initial`` of the wrong shape.
        SolveStopped: ``stop`` answered True.
    """
    _check(views, ridge, prior, iterations, degree, colour)
    check_finite(gaussians, (*GEOMETRY, "sh"))  # one NaN would spread through the system to every Gaussian
    num_bases = (min(degree, gaussians.sh_degree) + 1) ** 2
    if initial is not None and tuple(initial.shape) != (len(gaussians), num_bases, 3):
        raise ValueError(f"initial: expected shape {[len(gaussians), num_bases, 3]}, got {list(initial.shape)}")
    offsets = torch.zeros(len(gaussians), num_bases, 3) if initial is None else initial.detach().float().clone()
    if len(gaussians) == 0:
        return offsets
    A, b = colour_system(gaussians, views, backend, colour, stop)
    view_rows = np.cumsum([0] + [view.camera.height * view.camera.width for view in views]).astype(np.int64)
    means = gaussians.means.detach().numpy()
    bases = np.stack([sh_basis_at_points(means, view.camera.c2w64()[:3, 3], 1)[:, :num_bases] for view in views])
    system = (*_arrays(A), view_rows, bases)  # the basis once per view, not once per product
    no_x, no_y = np.zeros((0, num_bases, 3), np.float32), np.zeros((0, 3), np.float32)

    # one pass gives each Gaussian's block of A^T A (its diagonal: the evidence e_ik) and
    # A^T (A x0 - b), x0 the warm start
    gradient, blocks = _sh_products(*system, offsets.numpy() if initial is not None else no_x, b.numpy(), True)
    blocks = torch.from_numpy(blocks)  # [N, K, K]
    evidence = torch.diagonal(blocks, dim1=1, dim2=2)[..., None]  # [N, K, 1]: the same for every channel
    peak = torch.tensor([SH_C0, SH_C1, SH_C1, SH_C1][:num_bases])[None, :, None]
    damping = ridge * evidence + prior * peak**2
    # the preconditioner: each Gaussian's own block of the system, inverted (positive definite: a sum
    # of outer products plus the damping). A Gaussian seen from a narrow range of directions can hardly
    # tell its DC term from its linear ones; a diagonal preconditioner leaves that coupling to many steps
    inverse = torch.linalg.inv((blocks + torch.diag_embed(damping[..., 0])).double()).float()

    def precondition(r: Tensor) -> Tensor:  # [N, K, 3]
        return torch.einsum("nkl,nlc->nkc", inverse, r)

    def normal(x: Tensor) -> Tensor:  # (A^T A + diag(ridge e + prior peak^2)) x
        return torch.from_numpy(_sh_products(*system, x.numpy(), no_y, False)[0]) + damping * x

    # conjugate gradients, one step length per colour channel
    residual = -torch.from_numpy(gradient)
    if initial is not None:
        residual -= damping * offsets
    z = precondition(residual)
    direction, rz = z.clone(), (residual * z).sum((0, 1))
    for _ in range(iterations):
        _stop_if(stop)
        product = normal(direction)
        step = rz / (direction * product).sum((0, 1)).clamp_min(1e-30)
        offsets += step * direction
        residual -= step * product
        z = precondition(residual)
        rz_next = (residual * z).sum((0, 1))
        direction = z + (rz_next / rz.clamp_min(1e-30)) * direction
        rz = rz_next
    return offsets


def with_colour_offsets(gaussians: Gaussians, offsets: Tensor) -> Gaussians:  # offsets [N, K, 3]
    """``gaussians`` with ``offsets`` added to their first K SH coefficients."""
    sh = gaussians.sh.clone()
    sh[:, : offsets.shape[1], :] += offsets.to(sh)
    return replace(gaussians, sh=sh)


def solve_colours(
    gaussians: Gaussians,
    views: Sequence[Frame],  # the frames the scene was fused from: rgb and camera are used
    ridge: float = 0.3,
    prior: float = 1.0,
    iterations: int = 4,
    degree: int = 1,
    backend: WeightsBackend = "cpu",
    colour: Colour = "normalised",
) -> Gaussians:
    """``gaussians`` with SH coefficients up to ``degree`` (0: DC only; at most the Gaussians' own
    degree) offset so that their renders at ``views`` match the views' colours in the
    least-squares sense (module docstring), as rendered in ``colour`` mode (`rendering.render`).
    Geometry, opacity and higher coefficients are unchanged.

    Example (a scene fused from two synthetic views, colours solved against the same views):
        >>> from canonical_core.datasets import synthetic_rgbd
        >>> from canonical_core.scene import Scene, SceneConfig
        >>> frames = list(synthetic_rgbd(num_frames=2, width=64, height=48))
        >>> scene = Scene(SceneConfig(voxel_size=0.02))
        >>> reports = [scene.fold(f) for f in frames]
        >>> splats = scene.decode()
        >>> solved = solve_colours(splats, frames)
        >>> torch.equal(solved.means, splats.means), solved.sh.shape == splats.sh.shape
        (True, True)

    Raises:
        ValueError: no views, a view that is not a Frame, a negative ridge, a prior that is not
            positive, a non-positive iteration count, a degree other than 0 or 1, an unknown colour
            mode or weights backend.
    """
    return with_colour_offsets(gaussians, colour_offsets(gaussians, views, None, ridge, prior, iterations, degree, backend, colour))
