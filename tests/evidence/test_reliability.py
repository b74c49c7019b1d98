import numpy as np
import torch

from canonical_core import SceneConfig
from canonical_core.evidence import (AppearanceUncertainty, extract_evidence, positional_uncertainty,
                                     positional_uncertainty_reference, reliability, sensor_depth_std)

from ..conftest import make_frame


def test_fast_u_pos_equals_reference_with_holes_and_edges():
    rng = np.random.default_rng(0)
    depth = (0.3 + rng.random((20, 30)) * 0.1).astype(np.float32)
    depth[rng.random((20, 30)) < 0.4] = 0  # holes say nothing about edges
    depth[5:9, 10:14] += 0.5  # a real depth step
    std = (rng.random((20, 30)) * 0.003).astype(np.float32)
    rows, cols = np.nonzero(depth > 0)
    for s in (None, std):
        fast = positional_uncertainty(depth, rows, cols, 0.004, depth_std=s)
        ref = positional_uncertainty_reference(torch.from_numpy(depth), 0.004, None if s is None else torch.from_numpy(s))
        assert np.allclose(fast, ref.numpy()[rows, cols], rtol=1e-5, atol=1e-5)


def test_a_std_map_from_the_sensor_model_equals_no_std_map():
    # depth completion hands the fold an explicit std map; on measured pixels it must be the model
    depth = np.linspace(0.2, 1.6, 60, dtype=np.float32).reshape(6, 10)
    rows, cols = np.nonzero(depth > 0)
    model = positional_uncertainty(depth, rows, cols, 0.004, sigma0=0.002, sigma2=0.003, z_ref=0.5)
    explicit = positional_uncertainty(depth, rows, cols, 0.004, depth_std=sensor_depth_std(depth, 0.002, 0.003, 0.5))
    assert np.allclose(model, explicit, rtol=1e-6)
    assert sensor_depth_std(np.float32(0.5), 0.002, 0.003, 0.5) == np.float32(0.002)


def test_u_pos_is_in_voxel_units_so_reliability_ignores_the_unit():
    depth = np.full((6, 6), 2.0, np.float32)
    ev_m = extract_evidence(make_frame(depth, depth_std=np.full((6, 6), 0.01)), SceneConfig(voxel_size=0.02))
    ev_cm = extract_evidence(make_frame(depth * 100, depth_std=np.full((6, 6), 1.0)), SceneConfig(voxel_size=2.0, range={"far": 1e4}))
    assert np.allclose(ev_m.u_pos, 0.5) and np.allclose(ev_m.reliability, ev_cm.reliability)
    assert np.allclose(ev_m.reliability, np.exp(-0.5))


def test_sensor_model_makes_far_and_edge_pixels_less_reliable():
    depth = np.full((10, 10), 0.5, np.float32)
    depth[:, 5:] = 1.5  # a step: columns 4 and 5 are edge pixels
    ev = extract_evidence(make_frame(depth), SceneConfig(voxel_size=0.004))
    r = ev.reliability.reshape(10, 10)
    assert r[5, 0] > r[5, 9] > 0  # nearer is more reliable (sigma grows with z^2)
    assert r[5, 4] < 1e-3 * r[5, 0] and r[5, 5] < 1e-3 * r[5, 9]  # flying pixels on the step


def test_appearance_uncertainty_starts_at_zero_and_can_lower_reliability():
    app = AppearanceUncertainty(16)
    f = torch.randn(7, 16)
    assert app.is_zero and torch.equal(app(f), torch.zeros(7))
    depth = np.full((6, 6), 1.0, np.float32)
    frame = make_frame(depth)
    base = extract_evidence(frame, SceneConfig(voxel_size=0.01), app).reliability
    with torch.no_grad():
        app.mlp[2].bias.fill_(0.7)
    assert not app.is_zero
    lowered = extract_evidence(frame, SceneConfig(voxel_size=0.01), app).reliability
    assert np.allclose(lowered, base * np.exp(-0.7), rtol=1e-5)


def test_evidence_reliability_is_the_definition_exp_minus_u_pos_times_exp_minus_u_app():
    torch.manual_seed(0)
    app = AppearanceUncertainty(16)
    with torch.no_grad():  # an appearance module whose U_app differs from pixel to pixel
        app.mlp[2].weight.normal_(0.0, 2.0)
        app.mlp[2].bias.fill_(0.3)
    rng = np.random.default_rng(1)
    frame = make_frame(rng.uniform(0.5, 1.5, (9, 12)), rgb=rng.integers(0, 256, (9, 12, 3)), fx=6.0)
    ev = extract_evidence(frame, SceneConfig(voxel_size=0.01), app)
    with torch.no_grad():
        u_app = app(torch.from_numpy(ev.features))
    assert u_app.std() > 0.1  # the check below would not see the MLP's term otherwise
    expected = reliability(torch.from_numpy(ev.u_pos), u_app)
    assert np.allclose(ev.reliability, expected.numpy(), rtol=1e-5, atol=1e-12)


def test_observation_sh_basis_equals_the_renderers_definition():
    from canonical_core.evidence import observation_sh_basis
    from canonical_core.rendering.sh import sh_basis

    frame = make_frame(np.random.default_rng(0).uniform(0.5, 2.0, (7, 9)), fx=5.0)
    ev = extract_evidence(frame, SceneConfig(voxel_size=0.01))
    dirs = torch.from_numpy(ev.points) - frame.camera.center
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    for degree in (1, 2, 3):
        assert np.allclose(observation_sh_basis(ev, frame.camera, degree), sh_basis(dirs, degree).numpy(), atol=1e-6)
    assert observation_sh_basis(ev, frame.camera, 0).shape == (len(ev), 1)
