"""Free-space evidence: floaters that later (or earlier) frames see through vanish from the decode."""

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, SceneConfig
from canonical_core.decode import GaussianDecoder
from canonical_core.scene import Scene, aggregate_batch
from canonical_core.config import KEY_BITS, KEY_OFFSET
from canonical_core.gaussians.container import SH_C0
from canonical_core.scene.free_space import history_free_space_kernel, see_through_map

from ..conftest import make_frame

W, H, F = 64, 48, 100.0
VOXEL = 0.05


def wall_frame(x_offset: float, floater: bool) -> Frame:
    """A camera at (x_offset, 0, 0) facing a wall at z = 2; optionally a spurious patch at z = 1."""
    depth = np.full((H, W), 2.0, np.float32)
    if floater:
        depth[20:28, 28:36] = 1.0
    rgb = np.full((H, W, 3), 120, np.uint8)
    c2w = np.eye(4)
    c2w[0, 3] = x_offset
    cam = Camera([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1]], c2w, W, H)
    return Frame(rgb=rgb, camera=cam, depth=depth)


def floater_gaussians(scene: Scene) -> int:
    g = scene.decode()
    return int((g.means[:, 2] < 1.5).sum())


@pytest.mark.parametrize("floater_at", ["first", "last"])
def test_floater_seen_through_disappears(floater_at):
    offsets = [0.0, 0.08, -0.08, 0.15, -0.15]
    frames = [wall_frame(x, floater=(k == 0 if floater_at == "first" else k == len(offsets) - 1)) for k, x in enumerate(offsets)]
    with_fs, without = Scene(SceneConfig(voxel_size=VOXEL)), Scene(SceneConfig(voxel_size=VOXEL, free_space={"enabled": False}))
    for f in frames:
        with_fs.fold(f)
        without.fold(f)
    assert floater_gaussians(without) > 0
    assert floater_gaussians(with_fs) == 0
    # the wall stays: free space removes nothing that was seen where it is
    wall = lambda s: int((s.decode().means[:, 2] > 1.9).sum())  # noqa: E731
    assert wall(with_fs) == wall(without) > 100
    assert len(with_fs.decode()) <= len(without.decode())


def test_streaming_free_space_and_sh_equal_batch_and_ignore_order():
    offsets = [0.0, 0.08, -0.08, 0.15, -0.15]
    frames = [wall_frame(x, floater=(k == 2)) for k, x in enumerate(offsets)]
    config = SceneConfig(voxel_size=VOXEL)
    batch = aggregate_batch(frames, config)
    for order in ([0, 1, 2, 3, 4], [4, 2, 0, 3, 1]):
        scene = Scene(config)
        for i in order:
            scene.fold(frames[i])
        fields = scene.fields()
        assert torch.equal(fields["keys"], batch["keys"])
        assert torch.allclose(fields["free_space"], batch["free_space"], rtol=1e-5, atol=1e-4)
        floater = fields["position_mean"][:, 2] < 1.5
        assert floater.sum() >= 4 and (fields["free_space"][floater] > 0).all()
    # SH sums of a representative-stable set equal the batch's (uniform colour: no switches matter), to
    # the float16 rounding of the stored colour mean (at most 2^-11), which moves the DC term by it / C0
    assert torch.allclose(fields["sh"], batch["sh"], atol=2**-11 / SH_C0)


@pytest.mark.parametrize("weighting", ["no_reliability", "average"])
def test_ablations_without_reliability_count_see_through_rays_unweighted(weighting):
    # with reliability the rays count exp(-sigma / voxel) each; the ablations that set every
    # reliability to 1 must count them as 1 too, or support and free space are in different units
    sigma = 0.02
    frames = [wall_frame(x, floater=(k == 0)) for k, x in enumerate([0.0, 0.08, -0.08])]
    frames = [Frame(rgb=f.rgb, camera=f.camera, depth=f.depth, depth_std=torch.full_like(f.depth, sigma)) for f in frames]
    scenes = {w: Scene(SceneConfig(voxel_size=VOXEL, research={"weighting": w})) for w in ("full", weighting)}
    for scene in scenes.values():
        for f in frames:
            scene.fold(f)
    full, ablated = (scenes[w].fields(sort=True) for w in ("full", weighting))
    assert torch.equal(full["keys"], ablated["keys"])
    seen_through = full["free_space"] > 0
    assert seen_through.sum() >= 4
    ratio = full["free_space"][seen_through] / ablated["free_space"][seen_through]
    assert torch.allclose(ratio, torch.full_like(ratio, float(np.exp(-sigma / VOXEL))), rtol=1e-5)


@pytest.mark.parametrize("with_std", [False, True])
def test_see_through_map_equals_a_direct_per_cell_computation(with_std):
    # 21 x 27 pixels in 4-pixel cells: partial cells at the right and bottom, holes, NaN, depth past
    # far, ties for the nearest depth (the std is the first nearest pixel's, in row-major order)
    rng = np.random.default_rng(3)
    depth = rng.choice([0.6, 0.8, 1.0, 1.3], size=(21, 27)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[0, 0], depth[5, 9], depth[20, 26] = np.nan, 1e6, 0.7
    depth[8:12, 12:16] = 0.0  # an empty cell
    std = rng.uniform(0.001, 0.01, depth.shape).astype(np.float32)
    config = SceneConfig(voxel_size=0.01, free_space={"cell": 4})
    m = see_through_map(make_frame(depth, depth_std=std if with_std else None, fx=20.0), config)
    assert m.threshold.shape == m.weight.shape == (6, 7)
    for cy in range(6):
        for cx in range(7):
            d = depth[cy * 4:cy * 4 + 4, cx * 4:cx * 4 + 4].ravel()
            s = std[cy * 4:cy * 4 + 4, cx * 4:cx * 4 + 4].ravel()
            valid = (d > config.range.near) & (d < config.range.far)
            if not valid.any():
                assert m.threshold[cy, cx] == 0 and m.weight[cy, cx] == 0
                continue
            dmin = d[valid].min()
            sensor = config.sensor.in_effect(depth)  # the config leaves the family to the depth
            sigma = s[np.flatnonzero(valid & (d == dmin))[0]] if with_std else (
                sensor.sigma0 + sensor.sigma2 * (dmin - sensor.sigma_ref) ** 2)
            expect = dmin - (config.free_space.margin * config.voxel_size + config.free_space.sigmas * sigma)
            assert m.threshold[cy, cx] == pytest.approx(expect, rel=1e-6)
            assert m.weight[cy, cx] == pytest.approx(np.exp(-sigma / config.voxel_size) * valid.sum() / 16, rel=1e-5)


def test_history_bounds_the_retroactive_evidence():
    offsets = [0.0, 0.08, -0.08, 0.15, -0.15]
    frames = [wall_frame(x, floater=(k == 4)) for k, x in enumerate(offsets)]
    full, short = Scene(SceneConfig(voxel_size=VOXEL)), Scene(SceneConfig(voxel_size=VOXEL, free_space={"history": 2}))
    for f in frames:
        full.fold(f)
        short.fold(f)
    near = lambda s: s.fields()["free_space"][s.fields()["position_mean"][:, 2] < 1.5]  # noqa: E731
    assert (near(short) < near(full)).all()  # only the 2 most recent earlier frames counted


def test_opacity_is_non_increasing_in_free_space_for_any_weights():
    dec = GaussianDecoder(feature_dim=2)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in dec.free_space_penalty.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 5)
    n = 500
    fields = {
        "reliability": torch.full((n,), 2.0),
        "free_space": torch.linspace(0, 10, n),
        "features": torch.zeros(n, 2),
        "position_mean": torch.zeros(n, 3),
        "position_cov": torch.eye(3).repeat(n, 1, 1) * 1e-4,
        "colour": torch.full((n, 3), 0.5),
    }
    op = dec(fields, voxel_size=0.05).opacities
    assert (op[1:] - op[:-1] <= 1e-7).all() and op[0] > op[-1]


def test_snapshot_keeps_free_space_and_history(tmp_path):
    frames = [wall_frame(0.0, floater=True), wall_frame(0.1, floater=False)]
    scene = Scene(SceneConfig(voxel_size=VOXEL))
    scene.fold(frames[0])
    scene.save(tmp_path / "s.cgs")
    resumed = Scene.load(tmp_path / "s.cgs")
    scene.fold(frames[1])
    resumed.fold(frames[1])
    a, b = scene.sums(), resumed.sums()
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert (a["free"] > 0).any()


def test_voxel_centres_on_the_camera_plane_get_no_evidence_and_no_error():
    # a map whose camera puts every centre at depth 0: nothing is in front of it, nothing divides by 0
    keys = np.full(300, (KEY_OFFSET << (2 * KEY_BITS)) | (KEY_OFFSET << KEY_BITS) | KEY_OFFSET, np.int64)
    free = np.zeros(300, np.float32)
    P = np.zeros((1, 3, 4), np.float32)
    history_free_space_kernel(keys, free, 0, 300, np.float32(VOXEL), np.array([0]), P,
                              np.array([[10, 10, 2, 2]], np.float32), np.ones((1, 4, 4), np.float32),
                              np.ones((1, 4, 4), np.float32), np.array([[4, 4]]), np.ones(1, np.float32), np.float32(0.1))
    assert not free.any()


def _history_reference(keys, voxel, P, intr, thr, wcell, dims, area, near):
    """Each voxel centre tested against every map, in float32 as the kernel does: [V] evidence."""
    mask = (1 << KEY_BITS) - 1
    ijk = np.stack([(keys >> (2 * KEY_BITS)) & mask, (keys >> KEY_BITS) & mask, keys & mask], 1) - KEY_OFFSET
    centre = ((ijk.astype(np.int32).astype(np.float32) + np.float32(0.5)) * voxel).astype(np.float32)
    out = np.zeros(len(keys), np.float32)
    for e in range(P.shape[0]):
        xc, yc, zt = (P[e, r, 0] * centre[:, 0] + P[e, r, 1] * centre[:, 1] + P[e, r, 2] * centre[:, 2] + P[e, r, 3]
                      for r in range(3))
        zs = np.where(zt > near, zt, np.float32(1.0))
        u = intr[e, 0] * xc / zs + intr[e, 2] + np.float32(0.5)
        v = intr[e, 1] * yc / zs + intr[e, 3] + np.float32(0.5)
        h, w = dims[e]
        inside = (zt > near) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
        iu, iv = np.where(inside, np.floor(u), 0).astype(int), np.where(inside, np.floor(v), 0).astype(int)
        t = thr[e, iv, iu]
        seen = inside & (t > 0) & (zt < t)
        out += np.where(seen, wcell[e, iv, iu] * area[e] / np.where(seen, zt * zt, np.float32(1.0)), np.float32(0.0))
    return out


def test_history_evidence_skips_only_maps_that_cannot_see_a_block():
    # three clusters of voxels: in front of both cameras, across the edge of both frusta, behind both;
    # the kernel skips a block of voxels for a map whose frustum its box misses, which must change nothing
    rng = np.random.default_rng(0)

    def cluster(centre, n=300):
        ijk = np.round(np.asarray(centre) / VOXEL).astype(np.int64) + rng.integers(-4, 5, (n, 3))
        return ((ijk[:, 0] + KEY_OFFSET) << (2 * KEY_BITS)) | ((ijk[:, 1] + KEY_OFFSET) << KEY_BITS) | (ijk[:, 2] + KEY_OFFSET)

    keys = np.concatenate([cluster((0.0, 0.0, 1.5)), cluster((1.0, 0.0, 1.5)), cluster((0.0, 0.0, -1.5))])
    h, w = 12, 16
    P = np.zeros((2, 3, 4), np.float32)
    P[:, :, :3] = np.eye(3)
    P[1, 0, 3] = -0.3  # the second camera 0.3 m to the right of the first
    intr = np.array([[12.0, 12.0, 7.5, 5.5]] * 2, np.float32)  # a 16 x 12 map, 67 degrees wide
    thr = rng.uniform(1.0, 2.5, (2, h, w)).astype(np.float32)
    thr[:, :, :3] = 0.0  # cells without data
    wcell = rng.uniform(0.2, 1.0, (2, h, w)).astype(np.float32)
    dims, area = np.array([[h, w]] * 2), np.array([3e-3, 2e-3], np.float32)
    free = np.zeros(len(keys), np.float32)
    history_free_space_kernel(keys, free, 0, len(keys), np.float32(VOXEL), np.array([0, 1]), P, intr, thr, wcell,
                              dims, area, np.float32(0.1))
    expected = _history_reference(keys, np.float32(VOXEL), P, intr, thr, wcell, dims, area, np.float32(0.1))
    np.testing.assert_allclose(free, expected, rtol=1e-6, atol=0)
    assert (free[:300] > 0).mean() > 0.3  # in front of both: seen through where the maps say so
    assert 0 < (free[300:600] > 0).sum() < 300  # across the edges: some seen through, not all
    assert not free[600:].any()  # behind both cameras
