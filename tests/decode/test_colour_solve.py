"""solve_colours: the least-squares equations against a dense solve, invariants and errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from canonical_core.decode import colour_system, solve_colours
from canonical_core.frame import Frame
from canonical_core.gaussians import sh_dc_to_rgb
from canonical_core.rendering import render

from ..rendering.scenes import gaussians_at, look_at_camera, random_scene


def views_of(g, cameras, shift: float = 0.0) -> list[Frame]:
    """Frames showing ``g``'s own renders with every colour brightened by ``shift`` (the
    background stays black): what ``g`` with DC colours offset by ``shift`` renders."""
    frames = []
    for camera in cameras:
        out = render(g, camera, outputs=("rgb", "alpha"))
        rgb = (out.rgb + shift * out.alpha[..., None]).clamp(0, 1)
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
    solved = solve_colours(g, views, ridge=ridge, prior=prior, iterations=400)
    A, _, b = colour_system(g, views)
    A, b = A.to_dense().double(), b.double()
    evidence = (A**2).sum(0)
    expected = torch.linalg.solve(A.T @ A + torch.diag(ridge * evidence + prior), A.T @ b)
    offsets = sh_dc_to_rgb(solved.sh[:, 0]) - sh_dc_to_rgb(g.sh[:, 0])
    assert expected.abs().max() > 0.05  # the views disagree with the scene: there is something to solve
    assert torch.allclose(offsets.double(), expected, atol=2e-4)


def test_geometry_opacity_and_view_dependence_are_kept(scene):
    g, cameras = scene
    solved = solve_colours(g, views_of(g, cameras, shift=0.2))
    for name in ("means", "scales", "quats", "opacities"):
        assert torch.equal(getattr(solved, name), getattr(g, name))
    assert torch.equal(solved.sh[:, 1:], g.sh[:, 1:])
    assert not torch.equal(solved.sh[:, 0], g.sh[:, 0])


def test_renders_move_toward_the_views(scene):
    g, cameras = scene
    views = views_of(g, cameras, shift=0.15)

    def error(gaussians) -> float:
        return sum(float(((render(gaussians, v.camera, outputs=("rgb",)).rgb - v.rgb.float() / 255) ** 2).mean())
                   for v in views)  # fmt: skip

    assert error(solve_colours(g, views)) < 0.2 * error(g)


def test_an_offset_the_views_show_is_recovered(scene):
    g, cameras = scene
    solved = solve_colours(g, views_of(g, cameras, shift=0.15), ridge=0.0, prior=1e-3, iterations=200)
    offsets = sh_dc_to_rgb(solved.sh[:, 0]) - sh_dc_to_rgb(g.sh[:, 0])
    seen = colour_system(g, views_of(g, cameras))[0].to_dense().pow(2).sum(0) > 0.5  # well-seen Gaussians
    assert int(seen.sum()) > 20
    assert torch.allclose(offsets[seen], torch.full_like(offsets[seen], 0.15), atol=0.01)


def test_views_that_the_scene_already_renders_change_almost_nothing(scene):
    g, cameras = scene
    solved = solve_colours(g, views_of(g, cameras))
    # 8-bit rounding of the views is the only disagreement
    assert (sh_dc_to_rgb(solved.sh[:, 0]) - sh_dc_to_rgb(g.sh[:, 0])).abs().max() < 0.02


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
    ({"iterations": 2.5}, "iterations"), ({"backend": "gpu"}, "backend"),
])  # fmt: skip
def test_bad_arguments_name_the_field(scene, kwargs, field):
    g, cameras = scene
    arguments = {"views": views_of(g, cameras[:1])} | kwargs
    with pytest.raises(ValueError, match=field):
        solve_colours(g, **arguments)
