"""The streamed SH colour fit recovers known view-dependent colours."""

import numpy as np
import torch

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.rendering.sh import sh_basis, sh_to_rgb
from canonical_core.scene import Scene

SH_TRUE = np.array([[0.1, -0.2, 0.05], [0.25, 0.0, -0.1], [-0.15, 0.2, 0.0], [0.1, 0.1, 0.3]], np.float32)  # [4, 3]


def view_dependent_frame(centre) -> Frame:
    """A camera at ``centre`` looking at the plane z = 0 (from +z towards -z), whose colour at each
    point is 0.5 + SH_TRUE^T b(d) for the direction d from the camera to the point."""
    W = H = 40
    f = 60.0
    centre = np.asarray(centre, float)
    forward = -centre / np.linalg.norm(centre)  # look at the origin
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], 1)
    c2w[:3, 3] = centre
    cam = Camera([[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]], c2w, W, H)
    rays = cam.pixel_rays().reshape(-1, 3).double() @ torch.from_numpy(c2w[:3, :3]).T  # world directions, z-depth 1
    t = -centre[2] / rays[:, 2]  # hit z = 0
    points = torch.from_numpy(centre) + t[:, None] * rays
    depth = (t * 1.0).reshape(H, W).float()  # z-depth: camera z of the ray (unit z in camera frame) times t
    dirs = points - torch.from_numpy(centre)
    dirs = (dirs / dirs.norm(dim=1, keepdim=True)).float()
    colour = 0.5 + sh_basis(dirs, 1) @ torch.from_numpy(SH_TRUE)
    rgb = (colour.clamp(0, 1) * 255).round().to(torch.uint8).reshape(H, W, 3)
    return Frame(rgb=rgb, camera=cam, depth=depth)


def test_sh_fit_recovers_view_dependent_colour():
    rng = np.random.default_rng(0)
    centres = [np.r_[rng.uniform(-0.8, 0.8, 2), 1.0] for _ in range(12)]
    config = SceneConfig(voxel_size=0.1, research={"weighting": "average"}, decoder={"sh_regularization": 1e-6}, free_space={"enabled": False})
    scene = Scene(config)
    for c in centres:
        scene.fold(view_dependent_frame(c))
    f = scene.fields()
    well_seen = f["observations"] > 200
    assert well_seen.sum() > 5
    err = (f["sh"][well_seen] - torch.from_numpy(SH_TRUE)).abs()
    assert err.max() < 0.03  # uint8 colours and finite voxel extent bound the fit's accuracy


def test_regularisation_pulls_toward_the_dc_colour():
    frames = [view_dependent_frame(np.array([0.3, 0.1, 1.0]))]  # one direction: degree-1 terms unobservable
    scene = Scene(SceneConfig(voxel_size=0.1, research={"weighting": "average"}, free_space={"enabled": False}))
    scene.fold(frames[0])
    f = scene.fields()
    assert f["sh"][:, 1:].abs().max() < 0.1
    dc_colour = 0.5 + 0.28209479177387814 * f["sh"][:, 0]
    assert torch.allclose(dc_colour, f["colour"], atol=0.05)


def test_default_regularisation_keeps_view_dependence_seen_from_views_20_degrees_apart():
    # Two cameras 0.36 m apart at 1 m: each voxel is seen from directions ~20 degrees apart. The
    # default ridge must let the fit follow most of the colour change between them (a ridge of
    # 0.05 keeps 12 %, the default 70 %), while one view alone leaves it at the DC colour (test above).
    centres = [np.array([-0.18, 0.0, 1.0]), np.array([0.18, 0.0, 1.0])]
    scene = Scene(SceneConfig(voxel_size=0.1, research={"weighting": "average"}, free_space={"enabled": False}))
    for c in centres:
        scene.fold(view_dependent_frame(c))
    f = scene.fields()
    well_seen = f["observations"] > 50  # seen by both views (one view gives each voxel 11-31 pixels)
    assert well_seen.sum() > 3
    points = f["position_mean"][well_seen]
    dirs = [points - torch.from_numpy(c).float() for c in centres]
    truth = torch.from_numpy(SH_TRUE).expand(len(points), 4, 3)
    true_change = sh_to_rgb(truth, dirs[1]) - sh_to_rgb(truth, dirs[0])
    fitted_change = sh_to_rgb(f["sh"][well_seen], dirs[1]) - sh_to_rgb(f["sh"][well_seen], dirs[0])
    kept = (fitted_change * true_change).sum() / (true_change * true_change).sum()
    assert 0.5 < kept < 1.1
