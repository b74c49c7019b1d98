import numpy as np
import pytest
import torch
from dataclasses import replace

from canonical_core import Scene, SceneConfig
from canonical_core.evidence import denoise_rough_depth, depth_roughness, median_depth, sensor_depth_std
from canonical_core.evidence.denoise import MIN_SAMPLES, ROUGHNESS_LIMIT

from ..conftest import make_frame


def median_depth_reference(depth, radius):
    """Pure numpy: nanmedian over each valid pixel's window of valid depths, and the median's std."""
    H, W = depth.shape
    out, std = np.zeros_like(depth), np.zeros_like(depth)
    for v in range(H):
        for u in range(W):
            win = depth[max(v - radius, 0):v + radius + 1, max(u - radius, 0):u + radius + 1]
            win = win[win > 0]
            if depth[v, u] > 0 and win.size >= MIN_SAMPLES:
                out[v, u] = np.median(win)
                std[v, u] = 1.2533 * 1.4826 * np.median(np.abs(win - out[v, u])) / np.sqrt(win.size)
    return out, std


def noisy_plane(shape=(48, 64), z=0.5, noise=0.02, holes=0.3, seed=0):
    rng = np.random.default_rng(seed)
    depth = (z + noise * rng.standard_normal(shape)).astype(np.float32)
    depth[rng.random(shape) < holes] = 0.0
    return depth


def test_median_depth_equals_the_reference_with_holes():
    depth = noisy_plane((23, 31), holes=0.6)  # many windows near MIN_SAMPLES, borders included
    got, got_std = median_depth(depth, 2)
    want, want_std = median_depth_reference(depth, 2)
    assert np.array_equal(got > 0, want > 0) and (want == 0).any() and (want > 0).mean() > 0.2
    assert np.allclose(got, want, atol=1e-6) and np.allclose(got_std, want_std, rtol=1e-4, atol=1e-7)
    assert ((depth == 0) <= (got == 0)).all()  # the median fills no holes


def test_median_of_a_noisy_plane_is_close_to_it_and_its_std_is_honest():
    depth = noisy_plane(noise=0.02)
    smooth, std = median_depth(depth, 7)
    valid = smooth > 0
    error = smooth[valid] - 0.5
    assert np.abs(error).std() < 0.2 * 0.02  # ~ 1.25 * 0.02 / sqrt(157) = 0.002 plus border windows
    # the reported std is the median's own: within a factor 1.5 of the measured error
    assert 1 / 1.5 < np.median(std[valid]) / error.std() < 1.5


@pytest.mark.realdata
def test_roughness_tells_noise_from_clean_sensor_depth(shelf_frames):
    clean = shelf_frames[0].depth.numpy()
    sigma = sensor_depth_std(clean)
    rng = np.random.default_rng(1)
    rough = np.where(clean > 0, clean + 0.02 * rng.standard_normal(clean.shape), 0).astype(np.float32)
    assert depth_roughness(clean, sigma) < 1 < ROUGHNESS_LIMIT < 5 < depth_roughness(rough, sigma)
    # a per-pixel std that admits the noise makes the same depth not rough
    assert depth_roughness(rough, np.full_like(clean, 0.02)) < ROUGHNESS_LIMIT
    assert depth_roughness(np.zeros((4, 4), np.float32), np.ones((4, 4), np.float32)) == 0.0
    with pytest.raises(ValueError, match=r"sigma: expected the depth's shape \(480, 640\), got \(4, 4\)"):
        depth_roughness(clean, np.ones((4, 4), np.float32))
    with pytest.raises(ValueError, match="stride"):
        depth_roughness(clean, sigma, 0)


@pytest.mark.realdata
def test_denoise_leaves_clean_depth_untouched_and_replaces_rough_depth(shelf_frames):
    clean = shelf_frames[0].depth.numpy()
    args = (7, 0.0012, 0.0019, 0.4)
    depth, std = denoise_rough_depth(clean, None, *args)
    assert depth is clean and std is None
    rough = noisy_plane(noise=0.05)
    depth, std = denoise_rough_depth(rough, None, *args)
    assert np.array_equal(depth, median_depth(rough, 7)[0]) and std is not None
    assert denoise_rough_depth(rough, None, 0, *args[1:])[0] is rough  # radius 0: off
    with pytest.raises(ValueError, match="radius"):
        median_depth(rough, 0)


@pytest.mark.realdata
def test_fold_of_a_rough_frame_lifts_its_median_and_reports_it(shelf_frames):
    clean_frame = shelf_frames[0]
    rng = np.random.default_rng(2)
    d = clean_frame.depth.numpy()
    noisy = d + 0.05 * rng.standard_normal(d.shape)
    noisy_frame = replace(clean_frame, depth=torch.from_numpy(np.where((d > 0) & (noisy > 0), noisy, 0).astype(np.float32)))
    on, off = Scene(SceneConfig(voxel_size=0.004)), Scene(SceneConfig(voxel_size=0.004, depth={"denoise_radius": 0}))
    assert on.fold(noisy_frame).denoised and not off.fold(noisy_frame).denoised
    # denoised: far fewer voxels (the noise no longer scatters points along the rays), and the voxels
    # are where the clean depth puts the surface
    assert len(on) < 0.5 * len(off)  # measured 0.30
    truth = Scene(SceneConfig(voxel_size=0.004))
    assert not truth.fold(clean_frame).denoised

    def near_truth(scene):
        keys = scene.fields()["keys"]
        return torch.isin(keys, truth.fields()["keys"]).float().mean().item()

    assert near_truth(on) > 3 * near_truth(off)


@pytest.mark.realdata
def test_clean_frames_fold_identically_with_denoising_on_or_off(shelf_frames):
    # one explicit opacity line: without one, the decoder's intercept follows the denoising setting
    scenes = [Scene(SceneConfig(voxel_size=0.004, depth={"denoise_radius": r}, decoder={"opacity_bias": 0.0})) for r in (7, 0)]
    for scene in scenes:
        for f in shelf_frames[:3]:
            assert not scene.fold(f).denoised
    assert scenes[0].fields()["keys"].equal(scenes[1].fields()["keys"])
    assert torch.equal(scenes[0].decode().opacities, scenes[1].decode().opacities)


@pytest.mark.parametrize("bad", [-1, 33, 1.5, True])
def test_depth_denoise_radius_is_validated(bad):
    with pytest.raises(ValueError, match=r"^depth\.denoise_radius: "):
        SceneConfig(voxel_size=0.01, depth={"denoise_radius": bad})


def test_make_frame_depth_is_not_rough():
    # a hand-made constant-depth frame (the suite's usual fixture) is never denoised
    frame = make_frame(np.full((8, 8), 2.0))
    assert not Scene(SceneConfig(voxel_size=0.1)).fold(frame).denoised
