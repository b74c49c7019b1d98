import dataclasses
import io
import json

import numpy as np
import pytest
import torch

from canonical_core import SceneConfig
from canonical_core.scene import Scene

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def folded(shelf_frames):
    scene = Scene(SceneConfig(voxel_size=0.004))
    for f in shelf_frames[:6]:
        scene.fold(f)
    return scene


def test_save_load_is_bit_identical_and_decodes_identically(folded, tmp_path):
    folded.save(tmp_path / "scene.cgs")
    loaded = Scene.load(tmp_path / "scene.cgs")
    a, b = folded.sums(), loaded.sums()
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)
    assert loaded.frames == folded.frames and loaded.config == folded.config
    ga, gb = folded.decode(), loaded.decode()
    for name in ("means", "scales", "quats", "opacities", "sh", "features"):
        assert torch.equal(getattr(ga, name), getattr(gb, name)), name
    assert not list(tmp_path.glob("*.tmp"))


def test_snapshot_parts_encode_to_the_bytes_of_their_moment_while_later_folds_change_the_scene(shelf_frames, tmp_path):
    """`snapshot_parts` copies under the scene's lock: encoded after more folds (as the service writes a
    snapshot off the fold path), they give the bytes `to_bytes` gave then, into a file as into memory."""
    scene = Scene(SceneConfig(voxel_size=0.008, colour_solve={"views": 2}))  # kept views and history arrays too
    for f in shelf_frames[:3]:
        scene.fold(f)
    scene.decode()
    parts, then = scene.snapshot_parts(), scene.to_bytes()
    for f in shelf_frames[3:5]:
        scene.fold(f)
    assert scene.to_bytes() != then
    assert Scene.encode_snapshot(*parts) == then
    with open(tmp_path / "scene.snap", "wb") as out:
        assert Scene.encode_snapshot(*parts, out=out) is None
    assert (tmp_path / "scene.snap").read_bytes() == then


def test_save_load_keeps_the_opacity_line_settings(shelf_frames, tmp_path):
    scene = Scene(SceneConfig(voxel_size=0.004, decoder={"opacity_slope": 12.0, "opacity_bias": 0.5}))
    scene.fold(shelf_frames[0])
    scene.save(tmp_path / "scene.cgs")
    loaded = Scene.load(tmp_path / "scene.cgs")
    assert loaded.config.decoder.opacity_slope == 12.0 and loaded.config.opacity_bias == 0.5
    assert torch.equal(loaded.decode().opacities, scene.decode().opacities)


def test_folding_after_load_equals_uninterrupted(shelf_frames, folded, tmp_path):
    folded.save(tmp_path / "s.cgs")
    resumed = Scene.load(tmp_path / "s.cgs")
    straight = Scene(SceneConfig(voxel_size=0.004))
    for f in shelf_frames[:8]:
        straight.fold(f)
    for f in shelf_frames[6:8]:
        resumed.fold(f)
    a, b = straight.sums(), resumed.sums()
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_decoder_weights_travel_with_the_snapshot(folded):
    original = folded.decoder.opacity.b.item()
    with torch.no_grad():
        folded.decoder.opacity.b.fill_(-1.25)
    loaded = Scene.from_bytes(folded.to_bytes())
    assert loaded.decoder.opacity.b.item() == -1.25
    with torch.no_grad():
        folded.decoder.opacity.b.fill_(original)


def test_rejects_foreign_and_future_files(folded, tmp_path):
    with pytest.raises(ValueError, match="snapshot: not a readable scene file"):
        Scene.from_bytes(b"garbage")
    npz = dict(np.load(io.BytesIO(folded.to_bytes())))
    header = json.loads(npz["header"].tobytes()) | {"version": 9}
    npz["header"] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **npz)
    data = buf.getvalue()
    with pytest.raises(ValueError, match="version 9 is not supported"):
        Scene.from_bytes(data)
    npz["header"] = np.frombuffer(json.dumps(header | {"format": "another-format"}).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **npz)
    with pytest.raises(ValueError, match="snapshot: unknown format 'another-format'"):
        Scene.from_bytes(buf.getvalue())


def test_a_labelled_scene_saves_loads_and_folds_on_bit_identically(shelf_frames, tmp_path):
    """The label sums travel with the snapshot: the restored scene has the label channels, decodes
    the same label scores, and folding on stays bit-identical to the scene that never stopped."""
    def labelled(frame):  # three classes: the image's thirds
        labels = np.zeros((frame.height, frame.width, 3), np.float32)
        columns = np.arange(frame.width)
        labels[:, columns, np.minimum(columns * 3 // frame.width, 2)] = 1.0
        return dataclasses.replace(frame, labels=torch.from_numpy(labels))

    frames = [labelled(f) for f in shelf_frames[:3]]
    scene = Scene(SceneConfig(voxel_size=0.008))
    for f in frames[:2]:
        scene.fold(f)
    scene.save(tmp_path / "labelled.cgs")
    loaded = Scene.load(tmp_path / "labelled.cgs")
    assert loaded.label_dim == scene.label_dim == 3 and loaded.digest() == scene.digest()
    assert torch.equal(loaded.decode().labels, scene.decode().labels)
    scene.fold(frames[2])
    loaded.fold(frames[2])
    assert loaded.digest() == scene.digest()

    # a snapshot of the format before the label sums were stored as float16 means (version 6: float32
    # sums) loads into the scene the map would have stored from those sums
    npz = dict(np.load(io.BytesIO(scene.to_bytes())))
    mean = npz.pop("state.label_mean")
    npz["state.label_sum"] = mean.astype(np.float32) * npz["state.r_sum"][:, None]
    npz["header"] = np.frombuffer(json.dumps(json.loads(npz["header"].tobytes()) | {"version": 6}).encode(), np.uint8)
    assert mean.dtype == np.float16 and mean.shape[1] == 3
    buf = io.BytesIO()
    np.savez(buf, **npz)
    assert Scene.from_bytes(buf.getvalue()).digest() == scene.digest()


def test_digest_tracks_the_whole_state(folded, shelf_frames):
    loaded = Scene.from_bytes(folded.to_bytes())
    assert loaded.digest() == folded.digest()
    loaded.fold(shelf_frames[10])
    assert loaded.digest() != folded.digest()


def test_a_failed_save_leaves_no_temporary_file_and_names_the_path_given(tmp_path):
    (tmp_path / "scene.cgs").mkdir()
    with pytest.raises(IsADirectoryError) as err:
        Scene(SceneConfig(voxel_size=0.01)).save(tmp_path / "scene.cgs")
    assert err.value.filename == str(tmp_path / "scene.cgs")
    assert [p.name for p in tmp_path.iterdir()] == ["scene.cgs"]


def test_a_pickled_or_deep_copied_scene_is_its_snapshot_and_folds_on_alike(shelf_frames):
    """Pickling (a process pool's or a Ray task's argument) and `copy.deepcopy` carry the snapshot:
    the copy has the scene's digest and folds the next frame to the same digest."""
    import copy
    import pickle

    scene = Scene(SceneConfig(voxel_size=0.008))
    for f in shelf_frames[:2]:
        scene.fold(f)
    for twin in (pickle.loads(pickle.dumps(scene)), copy.deepcopy(scene)):
        assert type(twin) is Scene and twin is not scene and twin.digest() == scene.digest()
        twin.fold(shelf_frames[2])
    scene.fold(shelf_frames[2])
    assert twin.digest() == scene.digest()
