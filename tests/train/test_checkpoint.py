"""Decoder checkpoints: round trip, clear errors for corrupt or mismatched files, the `model` setting,
and snapshots that keep the model they were decoded with."""

from __future__ import annotations

import json

import pytest
import torch

from canonical_core.datasets import synthetic_rgbd
from canonical_core.decode import GaussianDecoder
from canonical_core.scene import Scene, SceneConfig
from canonical_core.train import (CHECKPOINT_VERSION, TRAINED_HEADS, apply_checkpoint, load_checkpoint, resolve_model,
                                  save_checkpoint)

VOXEL = 0.05


def perturbed(feature_dim: int = 16, seed: int = 0) -> GaussianDecoder:
    """A decoder whose every trained head differs from the analytic start."""
    decoder = GaussianDecoder(feature_dim)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in decoder.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
    return decoder


@pytest.fixture(scope="module")
def frames():
    return list(synthetic_rgbd(num_frames=3, width=48, height=36))


def scene_of(frames, **settings) -> Scene:
    scene = Scene(SceneConfig(voxel_size=VOXEL, **settings))
    for f in frames:
        scene.fold(f)
    return scene


def assert_same_gaussians(a, b):
    for name in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def test_round_trip_restores_every_trained_parameter(tmp_path):
    decoder = perturbed()
    path = save_checkpoint(tmp_path / "m.safetensors", decoder, {"seed": 3})
    checkpoint = load_checkpoint(path)
    assert checkpoint.heads == TRAINED_HEADS and checkpoint.settings == {"seed": 3} and checkpoint.feature_dim == 16
    fresh = GaussianDecoder(16)
    apply_checkpoint(fresh, checkpoint)
    for (name, p), q in zip(decoder.named_parameters(), fresh.parameters()):
        assert torch.equal(p, q), name


def test_the_same_decoder_saves_the_same_bytes(tmp_path):
    """A checkpoint's sha256 names the model that decoded a scene (its snapshot keeps it): the same
    decoder and settings must make the same file, every time and in every process."""
    decoder = perturbed()
    files = [save_checkpoint(tmp_path / f"m{k}.safetensors", decoder, {"seed": 3, "steps": 10}).read_bytes()
             for k in range(4)]
    assert all(f == files[0] for f in files)
    assert load_checkpoint(tmp_path / "m3.safetensors").settings == {"seed": 3, "steps": 10}


def test_scene_with_a_checkpoint_decodes_as_the_decoder_it_was_saved_from(tmp_path, frames):
    decoder = perturbed()
    path = save_checkpoint(tmp_path / "m.safetensors", decoder, {})
    trained = scene_of(frames, model=str(path))
    plain = scene_of(frames, model="none")
    plain.decoder.load_state_dict(decoder.state_dict())
    assert_same_gaussians(trained.decode(), plain.decode())
    assert trained.model_sha256 == load_checkpoint(path).sha256
    assert not torch.equal(trained.decode().opacities, scene_of(frames, model="none").decode().opacities)


def test_model_none_and_default_decode_as_the_training_free_decoder(frames):
    # the training-free decoder is the analytic one every scene had before checkpoints existed
    none, default = scene_of(frames, model="none"), scene_of(frames)
    reference = scene_of(frames, model="none")
    reference._decoding.decoder = GaussianDecoder(16, opacity_slope=reference.config.decoder.opacity_slope,
                                                  opacity_bias=reference.config.opacity_bias)
    assert_same_gaussians(none.decode(), reference.decode())
    if resolve_model("default") is None:
        assert_same_gaussians(default.decode(), reference.decode())
    assert none.digest() == default.digest()  # the model never changes the fused state
    assert none.model_sha256 is None


def test_snapshot_records_the_model_and_restores_without_the_file(tmp_path, frames):
    path = save_checkpoint(tmp_path / "m.safetensors", perturbed(), {})
    scene = scene_of(frames, model=str(path))
    data = scene.to_bytes()
    path.unlink()  # a restored session must not need the file
    restored = Scene.from_bytes(data)
    assert restored.config.model == str(path) and restored.model_sha256 == scene.model_sha256
    assert_same_gaussians(restored.decode(), scene.decode())


@pytest.mark.parametrize("value", ["", "weights.pt", "nonsense"])
def test_model_setting_is_validated(value):
    with pytest.raises(ValueError, match=r"^model: "):
        SceneConfig(voxel_size=VOXEL, model=value)


def _rewrite(path, tensors: dict, metadata: dict):
    from safetensors.torch import save_file

    save_file(tensors, str(path), metadata=metadata)


@pytest.fixture
def saved(tmp_path):
    path = save_checkpoint(tmp_path / "m.safetensors", perturbed(), {})
    checkpoint = load_checkpoint(path)
    from safetensors import safe_open

    with safe_open(str(path), "pt") as f:
        metadata = f.metadata()
    return path, dict(checkpoint.tensors), metadata


def test_truncated_file_is_a_clear_error(saved):
    path = saved[0]
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match=r"^model: .*not a readable safetensors file"):
        load_checkpoint(path)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match=r"^model: cannot read checkpoint"):
        load_checkpoint(tmp_path / "absent.safetensors")
    with pytest.raises(ValueError, match=r"^model: cannot read checkpoint"):
        Scene(SceneConfig(voxel_size=VOXEL, model=str(tmp_path / "absent.safetensors")))


def test_wrong_version_is_a_clear_error(saved):
    path, tensors, metadata = saved
    _rewrite(path, tensors, {**metadata, "version": str(CHECKPOINT_VERSION + 1)})
    with pytest.raises(ValueError, match=r"^model: .*checkpoint version '2'"):
        load_checkpoint(path)


def test_other_format_is_a_clear_error(saved):
    path, tensors, metadata = saved
    _rewrite(path, tensors, {k: v for k, v in metadata.items() if k != "format"})
    with pytest.raises(ValueError, match=r"^model: .*is not a decoder checkpoint"):
        load_checkpoint(path)


def test_missing_tensor_is_a_clear_error(saved):
    path, tensors, metadata = saved
    del tensors["decoder.offset.weight"]
    _rewrite(path, tensors, metadata)
    with pytest.raises(ValueError, match=r"^model: .*lacks tensor 'decoder.offset.weight'"):
        load_checkpoint(path)


def test_wrong_shape_is_a_clear_error(saved):
    path, tensors, metadata = saved
    tensors["decoder.color_delta.weight"] = torch.zeros(3, 8)
    _rewrite(path, tensors, metadata)
    with pytest.raises(ValueError, match=r"^model: tensor 'decoder.color_delta.weight' .*shape \[3, 8\], expected \[3, 16\]"):
        load_checkpoint(path)


def test_non_finite_tensor_is_a_clear_error(saved):
    path, tensors, metadata = saved
    tensors["decoder.opacity.w"] = torch.full_like(tensors["decoder.opacity.w"], float("nan"))
    _rewrite(path, tensors, metadata)
    with pytest.raises(ValueError, match=r"^model: tensor 'decoder.opacity.w' .*non-finite"):
        load_checkpoint(path)


def test_malformed_heads_are_a_clear_error(saved):
    path, tensors, metadata = saved
    _rewrite(path, tensors, {**metadata, "heads": json.dumps(["opacity", "laser"])})
    with pytest.raises(ValueError, match=r"^model: .*unknown heads"):
        load_checkpoint(path)


def test_feature_width_mismatch_is_a_clear_error(tmp_path, frames):
    path = save_checkpoint(tmp_path / "m8.safetensors", perturbed(feature_dim=8), {})
    with pytest.raises(ValueError, match=r"^model: the checkpoint's heads read 8 feature channels, the scene has feature_dim 16"):
        Scene(SceneConfig(voxel_size=VOXEL, model=str(path)))


def test_a_session_whose_model_cannot_load_is_refused_and_leaves_no_files(tmp_path):
    from server.store import SessionStore

    store = SessionStore(tmp_path / "data", max_sessions=4)
    store.open()
    try:
        before = sorted(p.name for p in (tmp_path / "data").iterdir())
        with pytest.raises(ValueError, match=r"^model: cannot read checkpoint"):
            store.create(SceneConfig(voxel_size=VOXEL, model=str(tmp_path / "absent.safetensors")))
        assert sorted(p.name for p in (tmp_path / "data").iterdir()) == before
        path = save_checkpoint(tmp_path / "m.safetensors", perturbed(), {})
        session = store.create(SceneConfig(voxel_size=VOXEL, model=str(path)))
        assert session.scene.model_sha256 == load_checkpoint(path).sha256
    finally:
        store.close()


def test_a_checkpoint_that_cannot_be_written_leaves_no_file_and_names_the_path(tmp_path):
    target = tmp_path / "m.safetensors"
    target.mkdir()  # a folder where the file would go
    with pytest.raises(IsADirectoryError, match="m.safetensors"):
        save_checkpoint(target, GaussianDecoder(16), {})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.safetensors"]
