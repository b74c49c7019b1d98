import numpy as np
import pytest
import torch

from canonical_core import Camera, Frame, Scene, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.frame import resize_frame
from canonical_core.resample import area_resize

CAM = Camera([[50.0, 0, 8], [0, 50.0, 6], [0, 0, 1]], np.eye(4), 16, 12)
RGB = np.zeros((12, 16, 3), np.uint8)


def test_valid_frame_and_missing_depth_normalised():
    depth = np.ones((12, 16), np.float32)
    depth[0, 0], depth[0, 1] = np.nan, np.inf
    f = Frame(rgb=RGB, camera=CAM, depth=depth, features=np.zeros((3, 4, 5), np.float32), labels=torch.zeros(6, 8, 2))
    assert f.depth[0, 0] == 0 and f.depth[0, 1] == 0 and f.depth[1, 1] == 1
    assert f.features.shape == (3, 4, 5) and f.labels.shape == (6, 8, 2) and f.has_depth


def test_depth_is_cleaned_as_the_torch_rule_has_it_from_any_float_input():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.0, 5.0, (12, 16)).astype(np.float32)
    depth[rng.random((12, 16)) < 0.2] = np.nan
    depth[rng.random((12, 16)) < 0.1] = np.inf
    reference = torch.from_numpy(depth.copy())
    reference = torch.where(torch.isfinite(reference), reference, torch.zeros_like(reference))
    read_only = np.frombuffer(depth.tobytes(), np.float32).reshape(12, 16)  # as a wire frame arrives
    for given in (depth, read_only, torch.from_numpy(depth).double(), np.asfortranarray(depth.astype(np.float64))):
        assert torch.equal(Frame(rgb=RGB, camera=CAM, depth=given).depth, reference)
    assert np.isnan(depth).any()  # the caller's array is left as it was
    with pytest.raises(ValueError, match="^depth: negative"):
        Frame(rgb=RGB, camera=CAM, depth=np.where(np.isnan(depth), -np.inf, depth).astype(np.float32))


@pytest.mark.parametrize(
    "kwargs, field, message",
    [
        (dict(rgb=np.zeros((12, 16), np.uint8)), "rgb", "shape"),
        (dict(rgb=np.zeros((12, 16, 3), np.float32)), "rgb", "uint8"),
        (dict(rgb=[[0]]), "rgb", "numpy"),
        (dict(rgb=np.zeros((10, 16, 3), np.uint8)), "camera", "does not match"),
        (dict(camera="cam"), "camera", "Camera"),
        (dict(depth=np.ones((12, 15), np.float32)), "depth", "shape"),
        (dict(depth=np.ones((6, 5), np.float32)), "depth", "does not have the shape of the rgb image 16x12"),
        (dict(depth=np.ones((24, 32), np.float32)), "depth", "larger than the rgb image"),
        (dict(depth=np.ones((6, 8), np.float32), depth_std=np.ones((12, 16), np.float32)), "depth_std", "shape"),
        (dict(depth=np.ones((12, 16), np.uint16)), "depth", "float"),
        (dict(depth=-np.ones((12, 16), np.float32)), "depth", "negative"),
        (dict(depth=np.ones((12, 16), np.float32), depth_std=np.full((12, 16), np.nan, np.float32)), "depth_std", "NaN"),
        (dict(depth=np.ones((12, 16), np.float32), depth_std=-np.ones((12, 16), np.float32)), "depth_std", "negative"),
        (dict(depth_std=np.ones((12, 16), np.float32)), "depth_std", "without depth"),
        (dict(features=np.zeros((4, 5), np.float32)), "features", "shape"),
        (dict(features=np.full((4, 5, 2), np.inf, np.float32)), "features", "NaN"),
        # a scene stores feature and label means in float16, which ends at 65504
        (dict(features=np.full((4, 5, 2), -1e5, np.float32)), "features", "largest magnitude 100000 exceeds 65504"),
        (dict(features=np.full((4, 5, 2), 1e300)), "features", "largest magnitude 1e+300 exceeds 65504"),
        (dict(features=np.full((4, 5, 4), 4e4, np.float32)), "features", "has norm 80000, above 65504"),
        (dict(labels=np.full((4, 5, 2), 7e4, np.float32)), "labels", "largest magnitude 70000 exceeds 65504"),
        (dict(labels=np.full((4, 5), 2**63, np.uint64), num_classes=3), "labels",
         "class 9223372036854775808 does not fit num_classes = 3"),
        (dict(labels=np.zeros((4, 5, 2), np.int64)), "labels", "float"),
        (dict(labels=np.zeros((4, 5), np.int64)), "num_classes", "required with a class map"),
        (dict(labels=np.full((4, 5), 3), num_classes=3), "labels", "class 3 does not fit num_classes = 3"),
        (dict(labels=np.zeros((4, 5), np.uint8), num_classes=0), "num_classes", "1..256"),
        (dict(labels=np.zeros((4, 5), np.uint8), num_classes=True), "num_classes", "required"),
        (dict(labels=np.zeros((4, 5, 2), np.float32), num_classes=3), "num_classes", "2 channels"),
        (dict(num_classes=3), "num_classes", "without labels"),
        (dict(labels=np.zeros((0, 5), np.int16), num_classes=3), "labels", "at least one pixel"),
        (dict(labels=np.zeros((4, 5), np.float32), num_classes=3), "labels", "integer class ids, got dtype torch.float32"),
        (dict(frame_id=5), "frame_id", "string"),
        (dict(frame_id="x" * 257), "frame_id", "at most 256 bytes"),
        (dict(frame_id="é" * 129), "frame_id", "got 258"),  # bytes of UTF-8, not characters
        (dict(frame_id="a\ud800"), "frame_id", "lone surrogate at character 1"),  # JSON carries it; no text holds it
    ],
)
def test_validation_names_field_and_problem(kwargs, field, message):
    args = dict(rgb=RGB, camera=CAM) | kwargs
    with pytest.raises(ValueError) as err:
        Frame(**args)
    assert str(err.value).startswith(field) and message in str(err.value)


def test_maps_at_any_resolution_are_taken():
    for shape in ((12, 16), (13, 16), (6, 8), (3, 4), (48, 64), (32, 32)):  # a square one: a network's output
        Frame(rgb=RGB, camera=CAM, labels=np.zeros(shape, np.int16), num_classes=2, features=np.zeros((*shape, 2), np.float32))


def test_a_class_map_is_kept_as_small_ids_with_its_k():
    ids = np.array([[0, 2, -1, -7], [1, 1, 0, 2]], np.int64)
    f = Frame(rgb=RGB, camera=CAM, labels=ids, num_classes=3)
    assert f.labels.dtype == torch.int16 and f.labels.tolist() == [[0, 2, -1, -1], [1, 1, 0, 2]]  # any negative: none
    assert f.num_classes == f.label_dim == 3
    scores = Frame(rgb=RGB, camera=CAM, labels=torch.ones(4, 5, 2), num_classes=2)
    assert scores.label_dim == 2 and scores.num_classes is None  # scores carry their K: num_classes is a map's
    assert Frame(rgb=RGB, camera=CAM, labels=np.ones((4, 5), bool), num_classes=2).labels.sum() == 20
    assert Frame(rgb=RGB, camera=CAM, labels=np.array([[0, 2]], np.uint8), num_classes=3).labels.tolist() == [[0, 2]]
    assert Frame(rgb=RGB, camera=CAM).label_dim is None


@pytest.mark.parametrize("dtype", [np.uint16, np.uint32, np.uint64, np.int8, np.int16, np.int32, np.int64,
                                   torch.uint16, torch.uint32, torch.uint64])
def test_a_class_map_of_any_integer_type_is_taken(dtype):
    # 16-bit label PNGs arrive as uint16; torch has no max of its unsigned types but uint8
    ids = [[0, 2, 1], [2, 2, 0]]
    labels = torch.tensor(ids).to(dtype) if isinstance(dtype, torch.dtype) else np.array(ids, dtype)
    f = Frame(rgb=RGB, camera=CAM, labels=labels, num_classes=3)
    assert f.labels.dtype == torch.int16 and f.labels.tolist() == ids and f.num_classes == 3
    with pytest.raises(ValueError, match="^labels: class 3 does not fit num_classes = 3"):
        Frame(rgb=RGB, camera=CAM, labels=labels + 1 if isinstance(labels, np.ndarray) else labels.to(torch.int64) + 1,
              num_classes=3)


def test_features_and_label_scores_up_to_the_float16_limit_fold_to_finite_means():
    frames = synthetic_rgbd(num_frames=2, width=64, height=48)
    scene = Scene(SceneConfig(voxel_size=0.02, features={"backend": "client", "dim": 4}))
    signs = np.where(np.arange(4 * 4 * 4).reshape(4, 4, 4) % 3, 1, -1).astype(np.float32)
    for frame in frames:  # each pixel's feature vector has norm 65504 exactly: the largest taken
        scene.fold(Frame(frame.rgb, frame.camera, frame.depth, features=signs * 32752,
                         labels=np.full((4, 4, 2), 65504, np.float32)))
    g = scene.decode()
    assert len(g) and torch.isfinite(g.features).all() and torch.isfinite(g.labels).all()
    assert g.labels.abs().max() >= 65000 and g.features.abs().max() > 30000


def test_depth_at_a_lower_resolution_takes_the_colour_to_its_pixels():
    # phone LiDAR and time-of-flight cameras register depth to the colour camera at a fraction of its
    # pixels: the frame is made at the depth's resolution, each pixel its footprint's mean colour
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    f = Frame(rgb=rgb, camera=CAM, depth=np.ones((6, 8), np.float32), depth_std=np.full((6, 8), 0.01, np.float32))
    assert f.rgb.shape == (6, 8, 3) and f.depth.shape == f.depth_std.shape == (6, 8)
    assert np.array_equal(f.rgb.numpy(), area_resize(rgb, (8, 6)))
    assert (f.camera.width, f.camera.height) == (8, 6) and np.allclose(f.camera.K64(), CAM.scaled(0.5).K64())
    # a pixel's ray is the same ray: the centre of depth pixel (u, v) sees what the image's 2x2 block around it saw
    assert np.allclose(f.camera.K64()[:2, 2], [(8 + 0.5) / 2 - 0.5, (6 + 0.5) / 2 - 0.5])
    # another shape within a pixel of the image's (rounded sizes): taken; the same frame built again is unchanged
    odd = Frame(rgb=rgb, camera=CAM, depth=np.ones((5, 7), np.float32))
    assert odd.rgb.shape == (5, 7, 3) and np.allclose(odd.camera.fx, 50 * 7 / 16)
    again = Frame(rgb=f.rgb, camera=f.camera, depth=f.depth)
    assert torch.equal(again.rgb, f.rgb) and np.array_equal(again.camera.K64(), f.camera.K64())


def test_a_frame_id_of_256_bytes_is_taken():
    assert Frame(rgb=RGB, camera=CAM, frame_id="x" * 256).frame_id == "x" * 256


def test_image_too_large_is_rejected():
    big = Camera([[50.0, 0, 8], [0, 50.0, 6], [0, 0, 1]], np.eye(4), 5000, 4000)
    with pytest.raises(ValueError, match="rgb: image of 5000x4000"):
        Frame(rgb=torch.zeros(4000, 5000, 3, dtype=torch.uint8), camera=big)


def test_resize_keeps_the_camera_consistent():
    frame = synthetic_rgbd(num_frames=1, width=64, height=48)[0]
    small = resize_frame(frame, 0.5)
    assert small.rgb.shape == (24, 32, 3) and small.depth.shape == (24, 32)
    assert small.camera.fx == pytest.approx(frame.camera.fx / 2)
    # nearest depth: every value of the small map is a value of the original
    assert np.isin(small.depth.numpy(), frame.depth.numpy()).all()
    assert resize_frame(frame, 1.0) is frame
    with pytest.raises(ValueError, match="scale"):
        resize_frame(frame, 1.5)


def test_read_only_arrays_are_accepted_without_a_warning(tmp_path):
    """An image read with PIL (np.asarray gives a read-only array) makes a Frame silently, and the
    Frame holds the same values in memory of its own."""
    from PIL import Image
    import warnings

    rgb = np.arange(12 * 16 * 3, dtype=np.uint8).reshape(12, 16, 3)
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    read = np.asarray(Image.open(tmp_path / "rgb.png"))
    depth = np.ones((12, 16), np.float32)
    depth.flags.writeable = False
    assert not read.flags.writeable
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = Frame(rgb=read, camera=CAM, depth=depth)
    assert torch.equal(f.rgb, torch.from_numpy(rgb)) and torch.equal(f.depth, torch.ones(12, 16))
    assert not np.shares_memory(f.rgb.numpy(), read)
