"""solve_colours and colour_offsets: the least-squares equations against a dense solve, invariants and errors."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numba
import numpy as np
import pytest
import torch

from canonical_core.decode import SolveStopped, colour_offsets, colour_system, solve_colours, with_colour_offsets
from canonical_core.decode.colour_solve import ROW_MIN_WEIGHT, _sh_products
from canonical_core.gaussians.container import SH_C0
from canonical_core.rendering.sh import SH_C1, sh_basis, sh_basis_at_points
from canonical_core.frame import Frame
from canonical_core.gaussians import sh_dc_to_rgb
from canonical_core.rendering import render
from canonical_core.rendering.projection import channel_values
from canonical_core.rendering.weights import blend_weights

from ..rendering.scenes import gaussians_at, look_at_camera, random_scene


def views_of(g, cameras, shift: float = 0.0, colour: str = "normalised") -> list[Frame]:
    """Frames showing ``g``'s own renders in ``colour`` mode with every colour brightened by
    ``shift`` (the background stays black): what ``g`` with DC colours offset by ``shift`` renders."""
    frames = []
    for camera in cameras:
        out = render(g, camera, outputs=("rgb", "alpha"), colour=colour)
        drawn = out.alpha if colour == "composited" else (out.alpha > 0).float()
        rgb = (out.rgb + shift * drawn[..., None]).clamp(0, 1)
        frames.append(Frame(rgb=(rgb.numpy() * 255 + 0.5).astype(np.uint8), camera=camera))
    return frames


@pytest.fixture(scope="module")
def scene():
    g = random_scene(60, seed=5, sh_degree=1, feature_dim=None, label_dim=None, opacity_range=(0.3, 0.9), spread=0.6)
    cameras = [look_at_camera(28, 22, 25.0, eye=[x, -0.3, -2.5], target=[0, 0, 0]) for x in (-0.8, 0.0, 0.7)]
    return g, cameras


def test_the_solution_is_the_dense_regularised_least_squares(scene):
    g, cameras = scene
    rng = np.random.default_rng(0)
    views = [Frame(rgb=rng.integers(0, 256, (c.height, c.width, 3), dtype=np.uint8), camera=c) for c in cameras]
    ridge, prior = 0.3, 0.5
    solved = solve_colours(g, views, ridge=ridge, prior=prior, iterations=400, degree=0)
    A, b = colour_system(g, views)
    A, b = A.to_dense().double(), b.double()
    evidence = (A**2).sum(0)
    expected = torch.linalg.solve(A.T @ A + torch.diag(ridge * evidence + prior), A.T @ b)
    offsets = sh_dc_to_rgb(solved.sh[:, 0]) - sh_dc_to_rgb(g.sh[:, 0])
    assert expected.abs().max() > 0.05  # the views disagree with the scene: there is something to solve
    assert torch.allclose(offsets.double(), expected, atol=2e-4)


@pytest.mark.parametrize("colour", ["composited", "normalised"])
def test_the_system_stacks_each_views_weights_and_residual(scene, colour):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.1)
    A, b = colour_system(g, views, colour=colour)
    pixels = cameras[0].height * cameras[0].width
    for i, (view, camera) in enumerate(zip(views, cameras)):
        w = blend_weights(g, camera, min_weight=ROW_MIN_WEIGHT)
        assert w.weights.min() >= ROW_MIN_WEIGHT and len(blend_weights(g, camera).weights) > len(w.weights)  # a tail was dropped
        rows = slice(i * pixels, (i + 1) * pixels)
        expected = torch.zeros(pixels, len(g)).index_put_((w.pixels, w.ids), w.weights)
        colours = channel_values(g, camera, ("rgb",)).double()  # [N, 3] as this view sees them
        out = render(g, camera, outputs=("rgb", "alpha"), colour=colour)
        covered = torch.ones(pixels, dtype=torch.bool)
        if colour == "normalised":  # rows over their alpha, only where the render covers the pixel
            alpha = expected.sum(1)
            covered = alpha >= 0.5
            assert 0.05 < covered.float().mean() < 0.95
            expected = torch.where(covered[:, None], expected / alpha.clamp_min(0.5)[:, None], torch.zeros_like(expected))
            assert (b[rows][~covered] == 0).all()
        else:  # each row scaled to the render's alpha: the dropped tail's weight shared in proportion
            kept = expected.sum(1)
            whole = render(g, camera, outputs=("alpha",)).alpha.reshape(-1)
            assert (whole >= kept - 1e-6).all() and (whole > kept + 1e-3).any()
            expected = expected * torch.where(kept > 0, whole / kept.clamp_min(1e-12), torch.ones_like(kept))[:, None]
        assert torch.allclose(A.to_dense()[rows], expected, atol=1e-6)
        # b is the view less its render (every weight in), where the rows cover the pixel
        residual = view.rgb.reshape(-1, 3).float() / 255 - out.rgb.reshape(-1, 3)
        assert torch.allclose(b[rows][covered], residual[covered], atol=1e-6)
        # the rows alone render the view up to the tails they leave out: a few hundredths at most
        # (where a tail is dark, the scaled row renders brighter; where it is bright, darker)
        render_rgb = out.rgb.reshape(-1, 3).double()
        unclamped = (render_rgb > 0) & (render_rgb < 1) & covered[:, None]  # render clamps to [0, 1]; the rows do not
        assert int(unclamped.sum()) > 100
        gap = (expected.double() @ colours - render_rgb)[unclamped].abs()
        assert gap.max() < 0.05 and gap.median() < 5e-3


def sh_system(g, views) -> tuple[torch.Tensor, torch.Tensor]:  # dense [R, N * 4] over (Gaussian, basis), b [R, 3]
    """The degree-1 system written out: column (i, k) is view v's weights of Gaussian i times Y_k(d_vi)."""
    A, b = colour_system(g, views)
    dense, rows = A.to_dense().double(), 0
    blocks = []
    for view in views:
        pixels = view.camera.height * view.camera.width
        d = g.means.double() - torch.from_numpy(view.camera.c2w64()[:3, 3])
        basis = sh_basis(d / d.norm(dim=-1, keepdim=True), 1)  # [N, 4]
        blocks.append((dense[rows:rows + pixels, :, None] * basis[None]).reshape(pixels, -1))
        rows += pixels
    return torch.cat(blocks), b.double()


def test_degree_1_is_the_dense_regularised_least_squares_over_sh_offsets(scene):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.1)
    ridge, prior = 0.3, 0.5
    solved = solve_colours(g, views, ridge=ridge, prior=prior, iterations=400, degree=1)
    M, b = sh_system(g, views)
    peak = torch.tensor([SH_C0, SH_C1, SH_C1, SH_C1], dtype=torch.float64).repeat(len(g))
    evidence = (M**2).sum(0)
    expected = torch.linalg.solve(M.T @ M + torch.diag(ridge * evidence + prior * peak**2), M.T @ b)
    offsets = (solved.sh[:, :4] - g.sh[:, :4]).double().reshape(-1, 3)
    assert expected[len(g):].abs().max() > 0.01  # linear terms take part
    assert torch.allclose(offsets, expected, atol=5e-4)
    # a warm start from anywhere reaches the same minimum; from the minimum itself, a step stays there
    start = torch.from_numpy(np.random.default_rng(3).normal(0.0, 0.2, (len(g), 4, 3)).astype(np.float32))
    warm = colour_offsets(g, views, start, ridge=ridge, prior=prior, iterations=400).double().reshape(-1, 3)
    assert torch.allclose(warm, expected, atol=5e-4)
    at_minimum = expected.float().reshape(len(g), 4, 3)
    stay = colour_offsets(g, views, at_minimum, ridge=ridge, prior=prior, iterations=1)
    assert torch.allclose(stay, at_minimum, atol=1e-4)


def test_the_sparse_products_equal_the_dense_ones_for_any_thread_count(scene):
    g, cameras = scene
    views = views_of(g, cameras)
    A, _ = colour_system(g, views)
    view_rows = np.cumsum([0] + [c.height * c.width for c in cameras]).astype(np.int64)
    centres = np.stack([c.c2w64()[:3, 3] for c in cameras])
    bases = np.stack([sh_basis_at_points(g.means.numpy(), centre, 1) for centre in centres])
    system = (A.crow_indices().numpy(), A.col_indices().numpy(), A.values().numpy(), view_rows, bases)
    M, _ = sh_system(g, views)
    rng = np.random.default_rng(1)
    x = rng.standard_normal((len(g), 4, 3)).astype(np.float32)
    y = rng.standard_normal((A.shape[0], 3)).astype(np.float32)
    no_x, no_y = np.zeros((0, 4, 3), np.float32), np.zeros((0, 3), np.float32)
    Mx, My = M @ torch.from_numpy(x).double().reshape(-1, 3), torch.from_numpy(y).double()
    normal, none = _sh_products(*system, x, no_y, False)  # A^T A x in one pass
    assert none.shape == (0, 4, 4)
    assert np.allclose(normal.reshape(-1, 3), (M.T @ Mx).numpy(), rtol=1e-4, atol=1e-4)
    assert (M.T @ Mx).abs().max() > 1.0  # not a comparison of zeros
    transposed, blocks = _sh_products(*system, no_x, y, True)  # -A^T y and each Gaussian's block of A^T A
    assert np.allclose(-transposed.reshape(-1, 3), (M.T @ My).numpy(), atol=1e-4)
    own = torch.stack([(M.T @ M)[4 * i: 4 * i + 4, 4 * i: 4 * i + 4] for i in range(len(g))])
    assert np.allclose(blocks, own.numpy(), atol=1e-4)
    assert own[:, 0, 1:].abs().max() > 0.01  # the DC and linear terms are coupled: not only a diagonal
    both, blocks_too = _sh_products(*system, x, y, True)  # A^T (A x - y)
    assert np.allclose(both.reshape(-1, 3), (M.T @ (Mx - My)).numpy(), rtol=1e-4, atol=1e-4)
    assert np.array_equal(blocks_too, blocks)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        for args, expected in (((x, no_y, False), normal), ((no_x, y, True), transposed), ((x, y, True), both)):
            assert np.array_equal(_sh_products(*system, *args)[0], expected)  # fixed view groups: bit-identical
        assert np.array_equal(_sh_products(*system, no_x, y, True)[1], blocks)
    finally:
        numba.set_num_threads(threads)


@pytest.mark.parametrize("degree", [0, 1])
def test_geometry_opacity_and_higher_coefficients_are_kept(degree):
    g = random_scene(60, seed=5, sh_degree=2, feature_dim=None, label_dim=None, opacity_range=(0.3, 0.9), spread=0.6)
    cameras = [look_at_camera(28, 22, 25.0, eye=[x, -0.3, -2.5], target=[0, 0, 0]) for x in (-0.8, 0.7)]
    solved = solve_colours(g, views_of(g, cameras, shift=0.2), degree=degree)
    for name in ("means", "scales", "quats", "opacities"):
        assert torch.equal(getattr(solved, name), getattr(g, name))
    solved_bases = (degree + 1) ** 2
    assert torch.equal(solved.sh[:, solved_bases:], g.sh[:, solved_bases:])
    for k in range(solved_bases):
        assert not torch.equal(solved.sh[:, k], g.sh[:, k])


@pytest.mark.parametrize("colour", ["composited", "normalised"])
def test_renders_move_toward_the_views(scene, colour):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.15, colour=colour)

    def error(gaussians, shown: str) -> float:  # on the pixels the scene covers
        total = 0.0
        for v in views:
            out = render(gaussians, v.camera, outputs=("rgb", "alpha"), colour=shown)
            total += float(((out.rgb - v.rgb.float() / 255) ** 2)[out.alpha >= 0.5].mean())
        return total

    solved = solve_colours(g, views, colour=colour)
    assert error(solved, colour) < 0.2 * error(g, colour)
    other = "composited" if colour == "normalised" else "normalised"
    # each fit is the better one in its own mode
    assert error(solved, colour) < error(solve_colours(g, views, colour=other), colour)


def colour_changes(solved, g, cameras) -> list[torch.Tensor]:  # per camera [N, 3]: colour seen, after - before
    """Before the clamp max(0, .) of the SH colour, which the fit leaves out."""
    changes = []
    for camera in cameras:
        d = g.means - torch.from_numpy(camera.c2w64()[:3, 3]).float()
        basis = sh_basis(d / d.norm(dim=-1, keepdim=True), g.sh_degree)
        changes.append(torch.einsum("nk,nkc->nc", basis, solved.sh - g.sh))
    return changes


@pytest.mark.parametrize("colour", ["composited", "normalised"])
@pytest.mark.parametrize("degree", [0, 1])
def test_an_offset_the_views_show_is_recovered(scene, degree, colour):
    g, cameras = scene
    solved = solve_colours(g, views_of(g, cameras, shift=0.15, colour=colour), ridge=0.0, prior=1e-3, iterations=200,
                           degree=degree, colour=colour)
    for camera, change in zip(cameras, colour_changes(solved, g, cameras)):
        seen = colour_system(g, views_of(g, [camera]), colour="composited")[0].to_dense().pow(2).sum(0) > 0.5  # well seen from it
        assert int(seen.sum()) > 15
        # the system's minimum itself is up to about 0.01 off the shift: the views are 8-bit, and the
        # rows keep the weights of at least ROW_MIN_WEIGHT, scaled to the pixel's whole weight
        assert torch.allclose(change[seen], torch.full_like(change[seen], 0.15), atol=0.015)


@pytest.mark.parametrize("colour", ["composited", "normalised"])
def test_views_that_the_scene_already_renders_change_almost_nothing(scene, colour):
    g, cameras = scene
    solved = solve_colours(g, views_of(g, cameras, colour=colour), colour=colour)
    # 8-bit rounding of the views is the only disagreement
    assert max(float(change.abs().max()) for change in colour_changes(solved, g, cameras)) < 0.02


def test_a_gaussian_no_view_sees_keeps_its_colour(scene):
    _, cameras = scene
    g = gaussians_at([[0, 0, 0], [0, 0, -9]], [[0.2] * 3, [0.2] * 3], [0.9, 0.9], [[0.2, 0.4, 0.6], [0.5, 0.5, 0.5]])
    g = replace(g, means=g.means.clone())
    g.means[1] = torch.tensor([0.0, 0.0, -5.0])  # behind every camera (they sit at z = -2.5 looking at +z)
    solved = solve_colours(g, views_of(g, cameras, shift=0.3))
    assert torch.equal(solved.sh[1], g.sh[1])
    assert not torch.equal(solved.sh[0], g.sh[0])


def test_no_gaussians_is_no_op(scene):
    g, cameras = scene
    empty = g.index(torch.zeros(0, dtype=torch.int64))
    assert len(solve_colours(empty, views_of(g, cameras[:1]))) == 0


@pytest.mark.parametrize("kwargs, field", [
    ({"views": []}, "views"), ({"views": "frame"}, "views"), ({"views": [None]}, r"views\[0\]"),
    ({"ridge": -1.0}, "ridge"), ({"ridge": "0.3"}, "ridge"), ({"prior": 0.0}, "prior"), ({"prior": float("inf")}, "prior"), ({"iterations": 0}, "iterations"),
    ({"iterations": 2.5}, "iterations"), ({"degree": 2}, "degree"), ({"colour": "bright"}, "colour"), ({"degree": 1.0}, "degree"), ({"backend": "gpu"}, "backend"),
])  # fmt: skip
def test_bad_arguments_name_the_field(scene, kwargs, field):
    g, cameras = scene
    arguments = {"views": views_of(g, cameras[:1])} | kwargs
    with pytest.raises(ValueError, match=field):
        solve_colours(g, **arguments)


def test_offsets_are_what_solve_colours_adds(scene):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.1)
    offsets = colour_offsets(g, views)
    assert offsets.shape == (len(g), 4, 3) and offsets.abs().max() > 0.05
    assert torch.equal(with_colour_offsets(g, offsets).sh, solve_colours(g, views).sh)


def test_a_warm_start_goes_on_from_where_it_starts(scene):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.1)
    converged = colour_offsets(g, views, iterations=200)
    # from the solution, a step stays there; from zero, one step is far from it
    assert (colour_offsets(g, views, converged, iterations=1) - converged).abs().max() < 1e-4
    assert (colour_offsets(g, views, iterations=1) - converged).abs().max() > 1e-2
    # from a part-way answer, 3 steps go on: closer than 3 steps from zero, about as close as 6 from zero
    part_way = colour_offsets(g, views, iterations=3)
    error = {name: float((x - converged).norm()) for name, x in (
        ("warm", colour_offsets(g, views, part_way, iterations=3)), ("cold 3", part_way),
        ("cold 6", colour_offsets(g, views, iterations=6)))}
    assert error["warm"] < 0.5 * error["cold 3"] and error["warm"] < 2 * error["cold 6"], error


def test_a_warm_start_of_the_wrong_shape_is_named(scene):
    g, cameras = scene
    with pytest.raises(ValueError, match=r"^initial: expected shape \[60, 4, 3\], got \[60, 1, 3\]"):
        colour_offsets(g, views_of(g, cameras[:1]), torch.zeros(len(g), 1, 3))


def test_stop_is_asked_before_each_view_and_each_step_and_ends_the_solve_when_it_says_so(scene):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.1)
    asked = []

    def never() -> bool:
        asked.append(len(asked))
        return False

    assert torch.equal(colour_offsets(g, views, iterations=5, stop=never), colour_offsets(g, views, iterations=5))
    assert len(asked) == len(views) + 5  # each view of the system, then each step of conjugate gradients
    for at in (0, len(views) - 1, len(views), len(views) + 4):  # in the system's views, then in the steps
        calls = itertools.count()
        with pytest.raises(SolveStopped):
            colour_offsets(g, views, iterations=5, stop=lambda: next(calls) == at)
        assert next(calls) == at + 1  # nothing asked after the answer that stopped it
