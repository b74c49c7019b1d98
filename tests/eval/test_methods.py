"""Methods: the registry, plain decoding, and the Open3D peer's ray cast."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame
from canonical_core.datasets import synthetic_rgbd
from canonical_core import SceneConfig
from canonical_core.decode import GaussianDecoder
from canonical_core.eval.baselines import full_support_opacity
from canonical_core.eval.methods import METHODS, build, check_methods, configured, parse_method
from canonical_core.eval.metrics import covered, psnr
from canonical_core.eval.open3d_tsdf import Open3DTSDF, open3d_available
from canonical_core.scene.keyframes import kept_view  # what a scene keeps of a view for its solve

from ..conftest import solved_as_kept

needs_open3d = pytest.mark.skipif(not open3d_available(), reason="needs the bench extra (open3d)")


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return list(synthetic_rgbd(num_frames=4, width=64, height=48))


def test_registry_names_the_issue_methods():
    assert list(METHODS) == ["canonical", "no_reliability", "no_similarity", "average", "plain_decoding",
                             "no_free_space", "no_view_dependence", "depth_completion", "colour_solve", "completion_solve",
                             "pixel_aligned", "gaussian_merge", "open3d_tsdf"]
    assert check_methods(["average", "canonical", "average"]) == ["average", "canonical"]
    with pytest.raises(ValueError, match="methods"):
        check_methods(["canonical", "nerf"])
    with pytest.raises(ValueError, match="methods"):
        check_methods("canonical")


def test_method_specs_carry_scene_settings_and_only_scene_methods_take_them():
    spec = parse_method("average:sh_degree=0:free_space.margin=3")
    assert spec.label == "average:sh_degree=0:free_space.margin=3.0"
    builder = spec.method().build
    assert builder.weighting == "average"
    assert builder.settings == {"sh_degree": 0, "free_space": {"margin": 3.0}}
    assert configured("no_free_space", {"free_space.margin": 3.0}).build.settings == {
        "free_space": {"enabled": False, "margin": 3.0}}  # merged with the method's own group
    with pytest.raises(ValueError, match="^methods:"):
        parse_method("pixel_aligned:sh_degree=0")
    with pytest.raises(ValueError, match="^methods:"):
        parse_method("nerf")
    with pytest.raises(ValueError, match="^no_such_setting:"):
        parse_method("canonical:no_such_setting=1")
    # the run's voxel is not a method's setting: refused before any run (it crashed the first build)
    with pytest.raises(ValueError, match=r"^methods: canonical:voxel_size is the run's.*\(--voxel-size\)"):
        parse_method("canonical:voxel_size=0.05")
    assert check_methods(["canonical:sh_degree=0", "canonical:sh_degree=0", "canonical"]) == ["canonical:sh_degree=0", "canonical"]


def test_a_method_setting_reaches_the_scene(frames):
    plain, _ = build("canonical", frames[:2], 0.02)
    degree0, _ = build("canonical:sh_degree=0", frames[:2], 0.02)
    assert plain.splats.sh.shape[1] > 1 and degree0.splats.sh.shape[1] == 1


@pytest.mark.skipif(open3d_available(), reason="checks the message of a machine where Open3D cannot be imported")
def test_a_missing_open3d_is_reported_with_its_import_error():
    reason = METHODS["open3d_tsdf"].unavailable()
    assert "pip install" in reason and "libusb" in reason
    error = reason.split("): ", 1)[1]  # the import's own error, e.g. "ModuleNotFoundError: No module named 'open3d'"
    assert error.split(": ", 1)[0].endswith("Error") and len(error.split(": ", 1)[1]) > 0


def test_plain_decoding_is_canonical_with_one_opacity(frames):
    canonical, _ = build("canonical", frames[:2], 0.02)
    plain, ms = build("plain_decoding", frames[:2], 0.02)
    assert ms > 0
    assert torch.equal(canonical.splats.means, plain.splats.means)
    assert not torch.allclose(canonical.splats.opacities, plain.splats.opacities)
    assert torch.allclose(plain.splats.opacities, torch.tensor(full_support_opacity(GaussianDecoder(16))))


def holed_frames() -> list[Frame]:
    """Three neighbouring synthetic views (~5 cm apart at ~1 m), the later two without depth in
    their left 60 columns (as a sensor's field of view or range would leave them)."""
    near = list(synthetic_rgbd(num_frames=48, width=160, height=120)[8:11])
    return [near[0]] + [dataclasses.replace(f, depth=torch.where(torch.arange(160) < 60, 0.0, f.depth)) for f in near[1:]]


def test_depth_completion_fills_what_the_sensor_missed():
    # completion fills the withheld band from the earlier views, canonical cannot
    holed = holed_frames()
    canonical, _ = build("canonical", holed, 0.02)
    completed, _ = build("depth_completion", holed, 0.02)
    assert completed.gaussians > canonical.gaussians
    band = lambda model: model.render(holed[2].camera).alpha[:, :60].mean()  # noqa: E731
    assert band(completed) > band(canonical) + 0.05


def test_canonical_solves_its_colours_against_its_inputs_by_default(frames):
    fused, _ = build("canonical:colour_solve.views=0", frames[:2], 0.02)
    canonical, _ = build("canonical", frames[:2], 0.02)
    solved, _ = build("colour_solve", frames[:2], 0.02)
    expected = solved_as_kept(fused.splats, [kept_view(f, SceneConfig(voxel_size=1).colour_solve.scale) for f in frames[:2]])
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(expected, name), getattr(solved.splats, name)), name
        assert torch.equal(getattr(expected, name), getattr(canonical.splats, name)), name
    assert not torch.equal(fused.splats.sh, solved.splats.sh)


def test_completion_solve_is_depth_completion_with_colours_solved():
    holed = holed_frames()
    completed, _ = build("depth_completion:colour_solve.views=0", holed, 0.02)
    both, _ = build("completion_solve", holed, 0.02)
    assert both.gaussians == completed.gaussians > build("canonical", holed, 0.02)[0].gaussians
    expected = solved_as_kept(completed.splats, [kept_view(f, SceneConfig(voxel_size=1).colour_solve.scale) for f in holed])
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(expected, name), getattr(both.splats, name)), name


def test_scene_methods_render_rgb_and_features(frames):
    model, _ = build("no_similarity", frames[:2], 0.02)
    view = model.render(frames[2].camera, features=True)
    assert view.features.shape == (48, 64, 16) and view.alpha.shape == (48, 64)
    view = model.render(frames[2].camera)
    assert view.rgb.shape == (48, 64, 3) and view.features is None
    assert float(view.alpha.max()) > 0.5


@needs_open3d
def test_tsdf_ray_cast_finds_the_integrated_surface(frames):
    frame = frames[1]
    tsdf = Open3DTSDF(0.01, block_count=256)
    tsdf.integrate(frame)
    rgb, depth = tsdf.ray_cast(frame.camera)
    hit = depth > 0
    seen = frame.depth > 0
    # at 64x48 a pixel is 2-3 voxels wide, so TSDF borders and grazing surfaces lose some pixels
    assert float((hit & seen).sum()) > 0.65 * float(seen.sum())
    assert float((hit & ~seen).sum()) < 0.01 * hit.numel()
    # Open3D's rule samples the voxel below the ray point (floor), so depth is good to a voxel
    assert float((depth - frame.depth)[hit & seen].abs().median()) < 0.01
    assert psnr(rgb, frame.rgb.float() / 255, hit) > 14.0
    away = Camera(K=frame.camera.K, c2w=frame.camera.c2w64() @ np.diag([-1.0, 1.0, -1.0, 1.0]), width=64, height=48)
    assert float(tsdf.ray_cast(away)[1].max()) == 0.0  # looking away from the scene: nothing


@needs_open3d
def test_tsdf_ray_cast_of_a_wall_and_the_weight_threshold():
    cam = Camera(K=[[40, 0, 15.5], [0, 40, 11.5], [0, 0, 1]], c2w=np.eye(4), width=32, height=24)
    wall = Frame(rgb=np.full((24, 32, 3), 200, np.uint8), camera=cam, depth=np.full((24, 32), 0.5, np.float32))
    tsdf = Open3DTSDF(0.01, block_count=64)
    tsdf.integrate(wall)
    rgb, depth = tsdf.ray_cast(cam)
    assert float((depth > 0).float().mean()) > 0.85  # the outermost pixels have no crossing
    assert torch.allclose(depth[depth > 0], torch.tensor(0.5), atol=0.01)
    assert torch.allclose(rgb[depth > 0], torch.tensor(200 / 255), atol=1e-3)
    assert float(tsdf.ray_cast(cam, weight_threshold=2.0)[1].max()) == 0.0  # one frame has weight 1
    tsdf.integrate(wall)
    assert float((tsdf.ray_cast(cam, weight_threshold=2.0)[1] > 0).float().mean()) > 0.85


@needs_open3d
def test_tsdf_method_has_no_gaussians_and_no_features(frames):
    model, _ = build("open3d_tsdf", frames[:2], 0.02)
    assert model.gaussians is None
    view = model.render(frames[2].camera)
    assert covered(view.alpha).any() and float(view.rgb[~covered(view.alpha)].abs().max()) == 0.0
    with pytest.raises(ValueError, match="features"):
        model.render(frames[2].camera, features=True)
