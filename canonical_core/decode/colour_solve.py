"""``solve_colours``: render-consistent colours, solved against the views the scene was fused from.

The analytic decoder gives each Gaussian its voxel's fused colour, a weighted mean of the pixels
that landed in the voxel. But a rendered pixel blends several overlapping Gaussians, so even a
view the scene was fused from does not get its own colours back (session 21 of
`docs/experiments.md`). With geometry and opacity fixed a render is linear in the colours,
colour(p) = sum_i w_i(p) c_i (`canonical_core.rendering.blend_weights`), so the colours that make
the renders reproduce the input views are a linear least-squares problem. This solves it for one
offset per Gaussian added to its DC colour (view dependence kept):

    min_delta  sum_views sum_p |sum_i w_i(p) delta_i - (I(p) - render(p))|^2
               + sum_i (ridge * d_i + prior) |delta_i|^2,      d_i = sum_views sum_p w_i(p)^2

by Jacobi-preconditioned conjugate gradients. ``ridge`` shrinks every offset relative to the
Gaussian's own evidence d_i; ``prior`` keeps the fused colour of Gaussians the views barely see
(hidden, or at the edge of the images), which the fit cannot determine. Training-free: no learned
weights, the same answer for the same scene and views.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from typing import Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ..frame import Frame
from ..gaussians import Gaussians
from ..gaussians.container import SH_C0
from ..rendering.projection import channel_values
from ..rendering.weights import WeightsBackend, blend_weights


def _check(views: Sequence[Frame], ridge: float, prior: float, iterations: int) -> None:
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


@numba.njit(cache=True)
def _counting_sort(rows: np.ndarray, num_rows: int) -> tuple[np.ndarray, np.ndarray]:  # row starts [R + 1], order [K]
    """Stable order of entries by row in O(K + R), and where each row starts (CSR's crow)."""
    starts = np.zeros(num_rows + 1, np.int64)
    for r in rows:
        starts[r + 1] += 1
    for r in range(num_rows):
        starts[r + 1] += starts[r]
    cursor = starts[:-1].copy()
    order = np.empty(rows.shape[0], np.int64)
    for k in range(rows.shape[0]):
        order[cursor[rows[k]]] = k
        cursor[rows[k]] += 1
    return starts, order


def colour_system(
    gaussians: Gaussians,
    views: Sequence[Frame],
    backend: WeightsBackend = "cpu",
) -> tuple[Tensor, Tensor, Tensor]:  # A: sparse CSR [P, N], its transpose [N, P], residual b [P, 3]
    """The linear system of the fit: A's rows are the views' pixels (view-major), its columns the
    Gaussians, its entries the compositing weights; b is each pixel's colour minus its render."""
    rows, columns, weights, residuals = [], [], [], []
    offset = 0
    for view in views:
        camera = view.camera
        w = blend_weights(gaussians, camera, backend=backend)
        colours = channel_values(gaussians, camera, ("rgb",)).float()
        render = torch.zeros(camera.height * camera.width, 3).index_add_(0, w.pixels, w.weights[:, None] * colours[w.ids])
        residuals.append(view.rgb.reshape(-1, 3).float() / 255.0 - render)
        rows.append(w.pixels + offset)
        columns.append(w.ids)
        weights.append(w.weights)
        offset += camera.height * camera.width
    rows, columns, weights = torch.cat(rows), torch.cat(columns), torch.cat(weights)
    size = (offset, len(gaussians))

    def csr(row: Tensor, column: Tensor, shape: tuple[int, int]) -> Tensor:  # each (row, column) occurs once
        row_starts, order = _counting_sort(row.numpy(), shape[0])
        row_starts, order = torch.from_numpy(row_starts), torch.from_numpy(order)
        with warnings.catch_warnings():  # torch flags sparse CSR as beta; its CPU matmul is what we need
            warnings.simplefilter("ignore", UserWarning)
            return torch.sparse_csr_tensor(row_starts, column[order], weights[order], shape)

    return csr(rows, columns, size), csr(columns, rows, size[::-1]), torch.cat(residuals)


def solve_colours(
    gaussians: Gaussians,
    views: Sequence[Frame],  # the frames the scene was fused from: rgb and camera are used
    ridge: float = 0.3,
    prior: float = 1.0,
    iterations: int = 10,
    backend: WeightsBackend = "cpu",
) -> Gaussians:
    """``gaussians`` with DC colours offset so that their renders at ``views`` match the views'
    colours in the least-squares sense (module docstring). Geometry and opacity are unchanged.

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
            positive, a non-positive iteration count, or an unknown weights backend.
    """
    _check(views, ridge, prior, iterations)
    if len(gaussians) == 0:
        return gaussians
    A, At, b = colour_system(gaussians, views, backend)
    evidence = torch.zeros(len(gaussians)).index_add_(0, A.col_indices(), A.values() ** 2)  # d_i
    damping = (ridge * evidence + prior)[:, None]
    diagonal = evidence[:, None] + damping

    def normal(x: Tensor) -> Tensor:  # (A^T A + diag(ridge d + prior)) x
        return At @ (A @ x) + damping * x

    # conjugate gradients, one step length per colour channel
    delta = torch.zeros(len(gaussians), 3)
    residual = At @ b
    z = residual / diagonal
    direction, rz = z.clone(), (residual * z).sum(0)
    for _ in range(iterations):
        product = normal(direction)
        step = rz / (direction * product).sum(0).clamp_min(1e-30)
        delta += step * direction
        residual -= step * product
        z = residual / diagonal
        rz_next = (residual * z).sum(0)
        direction = z + (rz_next / rz.clamp_min(1e-30)) * direction
        rz = rz_next
    sh = gaussians.sh.clone()
    sh[:, 0, :] += (delta / SH_C0).to(sh)
    return replace(gaussians, sh=sh)
