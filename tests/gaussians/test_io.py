import numpy as np
import pytest
import torch

from canonical_core import Gaussians, load_ply, load_splat, save_ply, save_splat
from canonical_core.gaussians import ply_bytes


def random_gaussians(n=50, degree=2, seed=0, features=4, labels=3):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 1e-3,
        quats=q / q.norm(dim=1, keepdim=True),
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g),
        features=torch.randn(n, features, generator=g) if features else None,
        labels=torch.rand(n, labels, generator=g) if labels else None,
    )


def test_ply_header_is_the_3dgs_layout():
    header = ply_bytes(random_gaussians(5, degree=1, features=0, labels=0)).split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    assert header.startswith("ply\nformat binary_little_endian 1.0\nelement vertex 5")
    assert props == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
                     *[f"f_rest_{i}" for i in range(9)], "opacity", "scale_0", "scale_1", "scale_2",
                     "rot_0", "rot_1", "rot_2", "rot_3"]
    assert all(line.startswith("property float ") for line in header.splitlines() if line.startswith("property"))


def test_ply_stores_logit_opacity_log_scale_and_channel_major_rest(tmp_path):
    g = random_gaussians(3, degree=1, features=0, labels=0)
    body = ply_bytes(g).split(b"end_header\n")[1]
    rows = np.frombuffer(body, np.float32).reshape(3, -1)
    op = g.opacities.double()
    assert np.allclose(rows[:, 18], torch.log(op / (1 - op)).numpy(), atol=1e-5)
    assert np.allclose(rows[:, 19:22], g.scales.log().numpy(), atol=1e-6)
    # f_rest_0..2 are the red channel's three degree-1 coefficients
    assert np.allclose(rows[:, 9:12], g.sh[:, 1:, 0].numpy())


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_ply_round_trip(tmp_path, degree):
    g = random_gaussians(degree=degree)
    save_ply(g, tmp_path / "g.ply")
    h = load_ply(tmp_path / "g.ply")
    for name in ("means", "sh", "features", "labels"):
        assert torch.equal(getattr(h, name), getattr(g, name)), name
    assert torch.allclose(h.scales, g.scales, rtol=1e-5)
    assert torch.allclose(h.opacities, g.opacities, atol=1e-5)
    assert torch.allclose(h.quats, g.quats, atol=1e-6)


def test_splat_round_trip_is_quantised(tmp_path):
    g = random_gaussians(features=0, labels=0)
    save_splat(g, tmp_path / "g.splat")
    assert (tmp_path / "g.splat").stat().st_size == 32 * len(g)
    h = load_splat(tmp_path / "g.splat")
    # rows come back sorted by volume x opacity; match them by position
    order = torch.cdist(h.means, g.means).argmin(1)
    assert torch.equal(h.means, g.means[order]) and torch.equal(h.scales, g.scales[order])
    assert (h.colours - g.colours[order]).abs().max() <= 0.5 / 255 + 1e-6
    assert (h.opacities - g.opacities[order]).abs().max() <= 0.5 / 255 + 1e-6
    cos = (h.quats * g.quats[order]).sum(1).abs()
    assert cos.min() > 0.999


def test_load_ply_rejects_garbage(tmp_path):
    (tmp_path / "x.ply").write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="ply: not a PLY"):
        load_ply(tmp_path / "x.ply")
    (tmp_path / "y.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        load_ply(tmp_path / "y.ply")


def test_container_validates_shapes():
    g = random_gaussians(4)
    with pytest.raises(ValueError, match=r"scales: expected shape \[4, 3\]"):
        Gaussians(means=g.means, scales=g.scales[:3], quats=g.quats, opacities=g.opacities, sh=g.sh)
    with pytest.raises(ValueError, match="sh: expected 1, 4, 9 or 16"):
        Gaussians(means=g.means, scales=g.scales, quats=g.quats, opacities=g.opacities, sh=torch.zeros(4, 5, 3))
    assert len(g.index(torch.tensor([0, 2]))) == 2
