import re

import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, Gaussians, load_ply, load_splat, render, save_ply, save_splat
from canonical_core.gaussians import SH_C0, ply_bytes, splat_bytes

THREE_DGS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]  # then f_rest_*, opacity, ...


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


def header_properties(data: bytes) -> list[tuple[str, str]]:  # (type, name) in header order
    header = data.split(b"end_header\n")[0].decode()
    return [tuple(line.split()[1:]) for line in header.splitlines() if line.startswith("property")]


def ply_rows(data: bytes) -> np.ndarray:  # the body as a structured array, read from the header
    types = {"float": "<f4", "uchar": "u1"}
    dtype = [(name, types[t]) for t, name in header_properties(data)]
    return np.frombuffer(data.split(b"end_header\n", 1)[1], dtype)


def test_ply_header_is_the_3dgs_layout_then_point_colours_then_extras():
    data = ply_bytes(random_gaussians(5, degree=1, features=2, labels=0))
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")
    # the 3DGS properties first and in their order (viewers that read by position still work), the
    # extras after them
    assert header_properties(data) == [
        *[("float", p) for p in THREE_DGS], *[("float", f"f_rest_{i}") for i in range(9)],
        *[("float", p) for p in ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")],
        ("uchar", "red"), ("uchar", "green"), ("uchar", "blue"), ("float", "feat_0"), ("float", "feat_1")]


def test_ply_point_colours_are_the_dc_colour_in_8_bits():
    g = random_gaussians(200, degree=2, features=0, labels=0)
    g.sh[:3, 0] = torch.tensor([[-10.0, 0.0, 10.0], [0.1, -0.1, 0.0], [1.77, -1.77, 0.0]])  # clamped, mid-grey, ~1/~0
    rows = ply_rows(ply_bytes(g))
    expected = np.clip(np.round((0.5 + SH_C0 * g.sh[:, 0]).numpy() * 255), 0, 255)  # float32, as written
    got = np.stack([rows["red"], rows["green"], rows["blue"]], 1)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[0], [0, 128, 255])
    assert got.min() == 0 and got.max() == 255


def test_open3d_reads_the_ply_as_a_coloured_point_cloud(tmp_path):
    try:
        import open3d
    except ImportError as exc:  # an optional extra: pip install -e ".[bench]"
        pytest.skip(f"open3d is not installed (the `bench` extra): {exc}")
    g = random_gaussians(100, degree=1)
    save_ply(g, tmp_path / "g.ply")
    cloud = open3d.io.read_point_cloud(str(tmp_path / "g.ply"))
    assert cloud.has_colors()
    np.testing.assert_allclose(np.asarray(cloud.points), g.means.numpy(), atol=1e-6)
    rows = ply_rows(ply_bytes(g))
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, np.stack([rows["red"], rows["green"], rows["blue"]], 1),
                               atol=1e-3)
    assert np.asarray(cloud.colors).std() > 0.05  # not one grey for all


def test_ply_stores_logit_opacity_log_scale_and_channel_major_rest(tmp_path):
    g = random_gaussians(3, degree=1, features=0, labels=0)
    rows = ply_rows(ply_bytes(g))
    op = g.opacities.double()
    assert np.allclose(rows["opacity"], torch.log(op / (1 - op)).numpy(), atol=1e-5)
    assert np.allclose(np.stack([rows[f"scale_{i}"] for i in range(3)], 1), g.scales.log().numpy(), atol=1e-6)
    # f_rest_0..2 are the red channel's three degree-1 coefficients
    assert np.allclose(np.stack([rows[f"f_rest_{i}"] for i in range(3)], 1), g.sh[:, 1:, 0].numpy())


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


@pytest.mark.parametrize("length", [1e-3, 7.0, 1e20])
def test_quaternions_of_any_length_are_written_and_read_as_rotations(tmp_path, length):
    """Trained 3DGS files keep rotations unnormalised: a quaternion of any length is the rotation of
    its unit form, in a PLY read and in both exports (float32 squares overflow from about 1e19)."""
    g = random_gaussians(features=0, labels=0)
    long = Gaussians(g.means, g.scales, g.quats * length, g.opacities, g.sh)
    rows = ply_rows(ply_bytes(long))
    assert np.allclose(np.stack([rows[f"rot_{i}"] for i in range(4)], 1), g.quats.numpy(), atol=1e-6)
    raw = bytearray(ply_bytes(g))
    body = np.frombuffer(raw, np.uint8)[raw.index(b"end_header\n") + 11:]
    table = body.view(ply_rows(bytes(raw)).dtype)
    for i in range(4):
        table[f"rot_{i}"] *= np.float32(length)
    (tmp_path / "long.ply").write_bytes(bytes(raw))
    assert torch.allclose(load_ply(tmp_path / "long.ply").quats, g.quats, atol=1e-6)
    save_splat(long, tmp_path / "long.splat")
    h = load_splat(tmp_path / "long.splat")
    order = torch.cdist(h.means, g.means).argmin(1)
    assert (h.quats * g.quats[order]).sum(1).abs().min() > 0.999


@pytest.mark.parametrize("kind", ["ply", "splat"])
def test_files_are_encoded_a_block_of_rows_at_a_time_in_a_fraction_of_their_size(tmp_path, kind):
    """`ply_file` / `splat_file` give the file's size before encoding and its bytes a block of rows at
    a time, equal to the whole encode's; writing one holds a block, not the file (a whole encode
    held four times the file: millions of Gaussians make hundreds of MB)."""
    import tracemalloc

    from canonical_core.gaussians import ENCODE_ROWS, ply_file, splat_file

    g = random_gaussians(n=24 * ENCODE_ROWS + 5, degree=1, features=16, labels=2)  # many blocks and a short last one
    encode, save, whole = {"ply": (ply_file, save_ply, ply_bytes), "splat": (splat_file, save_splat, splat_bytes)}[kind]
    file = encode(g)
    chunks = list(file.chunks)
    assert b"".join(chunks) == whole(g) and file.size == len(whole(g))
    assert len(chunks) == 25 + (kind == "ply") and max(map(len, chunks)) < file.size / 20
    tracemalloc.start()
    try:
        save(g, tmp_path / f"g.{kind}")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert (tmp_path / f"g.{kind}").read_bytes() == whole(g)
    # at most two blocks in flight; the .splat's order (8 bytes a row of its 32) is computed whole
    assert peak < file.size / (2 if kind == "splat" else 4), (peak, file.size)


def test_the_files_bytes_are_those_of_the_whole_file_encoder():
    """The blocks give the very bytes the files had when they were encoded whole (digests of that
    encoder's files of these Gaussians: several blocks, labels and features, rotations of any length)."""
    import hashlib

    from canonical_core.gaussians import ENCODE_ROWS, ply_file, splat_file

    g = torch.Generator().manual_seed(1)
    n = 40000
    assert n > 2 * ENCODE_ROWS
    gaussians = Gaussians(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), torch.randn(n, 4, generator=g),
                          torch.rand(n, generator=g), torch.randn(n, 4, 3, generator=g),
                          features=torch.randn(n, 5, generator=g), labels=torch.rand(n, 3, generator=g))
    assert hashlib.sha256(b"".join(ply_file(gaussians).chunks)).hexdigest() == \
        "456fce1c540ce1af44dec16e2f15c57d256cf66f610251b49e45f49728bbdfed"
    assert hashlib.sha256(b"".join(splat_file(gaussians).chunks)).hexdigest() == \
        "b65dc2bee8465e316967f14618d5721ba100f93ac320553e603c2adb4a5e8692"


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
    with pytest.raises(ValueError, match=f"^{re.escape(str(tmp_path / 'x.ply'))}: not a PLY"):
        load_ply(tmp_path / "x.ply")
    (tmp_path / "y.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="binary_little_endian"):
        load_ply(tmp_path / "y.ply")


def _edited_header(data: bytes, old: bytes, new: bytes) -> bytes:
    header, body = data.split(b"end_header\n", 1)
    assert old in header
    return header.replace(old, new, 1) + b"end_header\n" + body


@pytest.mark.parametrize(
    "old, new, message",
    [
        (b"format binary_little_endian 1.0", b"format", "malformed header line 'format'"),
        (b"element vertex 6", b"element vertex", "malformed header line 'element vertex'"),
        (b"element vertex 6", b"element vertex -1", "element 'vertex' has count '-1', expected a non-negative"),
        (b"element vertex 6", b"element vertex abc", "element 'vertex' has count 'abc'"),
        (b"property float nx", b"property", "malformed header line 'property'"),
        (b"property float nx", b"property float", "malformed header line 'property float'"),
        (b"property float nx", b"property float x", "vertex property 'x' appears twice"),
        (b"element vertex 6", b"element camera 1\nproperty float q\nelement vertex 6",
         "element 'camera' comes before the vertices"),  # its rows would be read as vertices
        # a file with one DC channel would be read as grey (the others zero)
        (b"property float f_dc_1\nproperty float f_dc_2", b"property float g_dc_1\nproperty float g_dc_2",
         r"missing 3DGS properties \['f_dc_1', 'f_dc_2'\]"),
        (b"property float scale_2", b"property float size_2", r"missing 3DGS properties \['scale_2'\]"),
        (b"property float f_rest_8", b"property float g_rest_8", "8 f_rest_\\* properties, expected 9, 24 or 45"),
    ],
)
def test_a_malformed_ply_is_refused_naming_the_file_and_the_problem(tmp_path, old, new, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(_edited_header(ply_bytes(random_gaussians(6, degree=1, features=0, labels=0)), old, new))
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: {message}"):
        load_ply(path)


def test_a_ply_with_windows_line_ends_and_small_integer_extras_is_read(tmp_path):
    """Other writers' PLYs: a header ended by CRLF, extra properties of the specification's small
    integer types (char, short, ushort) or their sized names (int8, int16, uint16)."""
    g = random_gaussians(6, degree=1, features=0, labels=0)
    header, body = ply_bytes(g).split(b"end_header\n", 1)
    header += b"property char a\nproperty int16 b\nproperty uint16 c\nproperty int8 d\n"
    rows = np.frombuffer(body, ply_rows(ply_bytes(g)).dtype)
    extra = np.dtype(rows.dtype.descr + [("a", "i1"), ("b", "<i2"), ("c", "<u2"), ("d", "i1")])
    joined = np.zeros(len(rows), extra)
    for name in rows.dtype.names:
        joined[name] = rows[name]
    path = tmp_path / "crlf.ply"
    path.write_bytes((header + b"end_header\n").replace(b"\n", b"\r\n") + joined.tobytes())
    h = load_ply(path)
    assert torch.equal(h.means, g.means) and torch.equal(h.sh, g.sh)


def test_a_ply_holding_nan_is_refused_naming_the_property(tmp_path):
    g = random_gaussians(6, degree=1, features=0, labels=0)
    raw = bytearray(ply_bytes(g))  # written by another tool: ours refuses NaN
    body = np.frombuffer(raw, np.uint8)[raw.index(b"end_header\n") + 11:]
    body.view(ply_rows(bytes(raw)).dtype)["y"][2] = np.nan
    path = tmp_path / "nan.ply"
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: NaN or inf in the properties \['y'\]"):
        load_ply(path)


def test_container_validates_shapes():
    g = random_gaussians(4)
    with pytest.raises(ValueError, match=r"scales: expected shape \[4, 3\]"):
        Gaussians(means=g.means, scales=g.scales[:3], quats=g.quats, opacities=g.opacities, sh=g.sh)
    with pytest.raises(ValueError, match="sh: expected 1, 4, 9 or 16"):
        Gaussians(means=g.means, scales=g.scales, quats=g.quats, opacities=g.opacities, sh=torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match=r"^means: expected shape \[N, 3\], got \[5\]"):
        Gaussians(means=torch.zeros(5), scales=g.scales, quats=g.quats, opacities=g.opacities, sh=g.sh)
    with pytest.raises(ValueError, match="^means: expected a floating-point tensor, got dtype torch.int64"):
        Gaussians(means=g.means.long(), scales=g.scales, quats=g.quats, opacities=g.opacities, sh=g.sh)
    assert repr(render(g, Camera(np.eye(3), np.eye(4), 4, 3), outputs=("rgb", "alpha"))) == \
        "RenderResult(rgb=[3, 4, 3], alpha=[3, 4])"  # shapes, not pixels
    assert len(g.index(torch.tensor([0, 2]))) == 2


@pytest.mark.parametrize("save", [save_ply, save_splat], ids=["ply", "splat"])
def test_a_failed_save_leaves_no_temporary_file_and_names_the_path_given(save, tmp_path):
    (tmp_path / "a.ply").mkdir()  # a folder where the file should go: the rename fails after the write
    with pytest.raises(IsADirectoryError) as err:
        save(random_gaussians(5), tmp_path / "a.ply")
    assert err.value.filename == str(tmp_path / "a.ply")
    with pytest.raises(FileNotFoundError) as err:  # a missing folder: the temporary file cannot be opened
        save(random_gaussians(5), tmp_path / "missing" / "b.ply")
    assert err.value.filename == str(tmp_path / "missing" / "b.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply"]


@pytest.mark.parametrize("field", ["means", "scales", "quats", "opacities", "sh"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_or_inf_in_gaussians_is_refused_naming_the_field_where_they_are_used(tmp_path, field, bad):
    """A render would drop a Gaussian with a NaN mean (or draw NaN), and one NaN in a colour solve's
    system would blacken every Gaussian it fits: render, the blend weights, the colour solve and the
    exports refuse NaN or inf, naming the field."""
    from canonical_core.rendering.weights import blend_weights
    from canonical_core.decode import colour_offsets

    g = random_gaussians(features=0, labels=0)
    getattr(g, field).view(-1)[7] = bad
    camera = Camera(K=[[40, 0, 15.5], [0, 40, 11.5], [0, 0, 1]], c2w=np.eye(4), width=32, height=24)
    frame = Frame(rgb=np.zeros((24, 32, 3), np.uint8), camera=camera)
    for call in (lambda: render(g, camera), lambda: render(g, camera, backend="reference"),
                 lambda: colour_offsets(g, [frame]), lambda: save_ply(g, tmp_path / "g.ply"),
                 lambda: save_splat(g, tmp_path / "g.splat")):
        with pytest.raises(ValueError, match=f"^{field}: NaN or inf"):
            call()
    if field != "sh":  # the weights read where Gaussians are and how opaque, not their colours
        with pytest.raises(ValueError, match=f"^{field}: NaN or inf"):
            blend_weights(g, camera)
    assert not list(tmp_path.iterdir())


def test_a_ply_whose_log_scales_overflow_and_a_splat_with_nan_are_refused_naming_the_file(tmp_path):
    g = random_gaussians(features=0, labels=0)
    raw = bytearray(ply_bytes(g))
    body = np.frombuffer(raw, np.uint8)[raw.index(b"end_header\n") + 11:]
    body.view(ply_rows(bytes(raw)).dtype)["scale_0"][3] = 100.0
    (tmp_path / "big.ply").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"big\.ply: scale_\* properties over 88"):
        load_ply(tmp_path / "big.ply")
    data = bytearray(splat_bytes(g))
    np.frombuffer(data, np.float32)[0] = np.nan  # the first row's x
    (tmp_path / "nan.splat").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"nan\.splat: NaN or inf in the position"):
        load_splat(tmp_path / "nan.splat")
    (tmp_path / "short.splat").write_bytes(bytes(data[:-2]))
    with pytest.raises(ValueError, match=r"short\.splat: file size"):
        load_splat(tmp_path / "short.splat")


def test_a_field_found_finite_is_checked_again_once_it_changes():
    from canonical_core.gaussians.container import check_finite

    g = random_gaussians(features=0, labels=0)
    check_finite(g)
    g.means[3, 0] = float("nan")  # in place: the tensor's version moves on
    with pytest.raises(ValueError, match="^means: NaN or inf"):
        check_finite(g)
    g.means = torch.zeros_like(g.means)  # another tensor
    check_finite(g)
    g.sh = torch.full_like(g.sh, float("inf"))
    with pytest.raises(ValueError, match="^sh: NaN or inf"):
        check_finite(g)


def test_a_new_tensor_at_a_freed_ones_address_is_checked_and_float64_does_not_overflow():
    """The check's memory is of tensor objects, not addresses: a NaN tensor made where a checked one
    was freed is tested (a reused id with a fresh version counter would have passed); float64 values
    that would overflow a sum are finite."""
    import gc

    from canonical_core.gaussians.container import check_finite

    g = random_gaussians(features=0, labels=0)
    n, reused = len(g), 0
    for _ in range(50):  # an id is often reused once the old tensor is gone
        check_finite(g, ("means",))
        address = id(g.means)
        g.means = None
        gc.collect()
        g.means = torch.full((n, 3), float("nan"))
        reused += id(g.means) == address
        with pytest.raises(ValueError, match="^means: NaN or inf"):
            check_finite(g, ("means",))
        g.means = torch.zeros(n, 3)
    assert reused  # the case this guards against did happen here
    g.scales = torch.full((n, 3), 1e307, dtype=torch.float64)
    check_finite(g, ("scales",))
