"""Checkpoints of the trained decoder: safetensors files with a versioned header.

A checkpoint holds the parameters of the `decode.GaussianDecoder` heads that training changes,
each under ``decoder.<parameter>``, and in the safetensors metadata (strings):

- ``format``: ``"canonicalgs-decoder"``, ``version``: `CHECKPOINT_VERSION`;
- ``feature_dim``: L, the channels of F_scene the heads read;
- ``heads``: JSON list of the trained heads (`TRAINED_HEADS` names);
- ``settings``: JSON of the training settings (captures, seed, steps, resolution, ...).

`load_checkpoint` checks all of it and raises a ValueError that starts with ``model:`` and names
the problem (unreadable or truncated file, another format or version, a missing or extra tensor, a
tensor of the wrong shape or with non-finite values). `resolve_model` turns the `SceneConfig.model`
setting into a checkpoint path (or None for the training-free decoder). Checkpoints are written by
``canonical train`` (`canonical_core.train`); they live here, below the scene, because every scene
loads one.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from .decoder import GaussianDecoder

CHECKPOINT_FORMAT = "canonicalgs-decoder"
CHECKPOINT_VERSION = 1
# The decoder's heads, by module name: the two monotone opacity heads and the three on F_scene.
TRAINED_HEADS = ("opacity", "free_space_penalty", "offset", "log_scale_delta", "color_delta")
# The checkpoint `SceneConfig(model="default")` loads, a file in `SHIPPED_FOLDER`; None: "default"
# is the training-free decoder (no trained checkpoint measured better on the evaluation capture:
# docs/training.md). A shipped file also needs its pyproject.toml package-data entry.
SHIPPED_CHECKPOINT: str | None = None
SHIPPED_FOLDER = Path(__file__).parent / "checkpoints"


@dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint: the decoder parameters and what the header says about them."""

    tensors: dict[str, Tensor]  # "decoder.<parameter>" -> tensor
    feature_dim: int
    heads: tuple[str, ...]
    settings: dict = field(default_factory=dict)
    sha256: str = ""  # of the file's bytes: which model decoded a scene (`Scene` snapshots record it)


def decoder_tensors(decoder: GaussianDecoder, heads: tuple[str, ...] = TRAINED_HEADS) -> dict[str, Tensor]:
    """The parameters of ``heads`` as checkpoint tensors (detached, contiguous float32 copies)."""
    return {f"decoder.{name}": p.detach().to(torch.float32).contiguous().clone()
            for name, p in decoder.named_parameters() if name.split(".")[0] in heads}


def save_checkpoint(path: str | os.PathLike, decoder: GaussianDecoder, settings: dict,
                    heads: tuple[str, ...] = TRAINED_HEADS) -> Path:
    """Write ``decoder``'s ``heads`` and the training ``settings`` (JSON-serialisable) to ``path``,
    atomically (a failed write leaves no file, and its OSError names ``path``)."""
    from safetensors.torch import save

    from ..gaussians.io import atomic_write

    unknown = [h for h in heads if h not in TRAINED_HEADS]
    if unknown or not heads:
        raise ValueError(f"heads: expected a non-empty subset of {list(TRAINED_HEADS)}, got {list(heads)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    metadata = {"format": CHECKPOINT_FORMAT, "version": str(CHECKPOINT_VERSION), "feature_dim": str(decoder.feature_dim),
                "heads": json.dumps(list(heads)), "settings": json.dumps(settings, sort_keys=True)}
    atomic_write(path, [_stable_header(save(decoder_tensors(decoder, heads), metadata=metadata))])
    return path


def _stable_header(blob: bytes) -> bytes:
    """A safetensors file with its JSON header's keys sorted: safetensors writes its metadata in a hash
    map's order, which changes from call to call, so the same decoder made files of other bytes (and
    another `model_sha256`, which names the model that decoded a scene). Offsets in the header count
    from the end of the header, so only the header changes; it stays padded to 8 bytes, as written."""
    size = int.from_bytes(blob[:8], "little")
    header = json.dumps(json.loads(blob[8:8 + size]), sort_keys=True, separators=(",", ":"))
    header += " " * (-len(header) % 8)
    return len(header).to_bytes(8, "little") + header.encode("utf-8") + blob[8 + size:]


def _header(metadata: dict[str, str] | None, path: Path) -> tuple[int, tuple[str, ...], dict]:
    """(feature_dim, heads, settings) from the safetensors metadata, checked."""
    meta = metadata or {}
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"model: {path} is not a decoder checkpoint (format {meta.get('format')!r}, "
                         f"expected {CHECKPOINT_FORMAT!r})")
    if meta.get("version") != str(CHECKPOINT_VERSION):
        raise ValueError(f"model: {path} has checkpoint version {meta.get('version')!r}; this library reads "
                         f"version {CHECKPOINT_VERSION}")
    try:
        feature_dim = int(meta["feature_dim"])
        heads = tuple(json.loads(meta["heads"]))
        settings = json.loads(meta.get("settings", "{}"))
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"model: {path} has a malformed header ({type(exc).__name__}: {exc})") from None
    if not heads or any(h not in TRAINED_HEADS for h in heads):
        raise ValueError(f"model: {path} names unknown heads {list(heads)}; expected some of {list(TRAINED_HEADS)}")
    return feature_dim, heads, settings


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read and check a checkpoint (module docstring); raises ValueError ``"model: ..."``."""
    from safetensors import SafetensorError
    from safetensors.torch import load

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"model: cannot read checkpoint {path} ({exc.strerror or exc})") from None
    try:
        tensors = load(data)
        metadata = _metadata(data)
    except (SafetensorError, ValueError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"model: {path} is not a readable safetensors file (truncated or corrupt: {exc})") from None
    feature_dim, heads, settings = _header(metadata, path)
    expected = decoder_tensors(GaussianDecoder(feature_dim), heads)
    for name in expected:
        if name not in tensors:
            raise ValueError(f"model: {path} lacks tensor {name!r}")
    for name, tensor in tensors.items():
        if name not in expected:
            raise ValueError(f"model: {path} has an unexpected tensor {name!r}")
        if tensor.shape != expected[name].shape:
            raise ValueError(f"model: tensor {name!r} of {path} has shape {list(tensor.shape)}, expected "
                             f"{list(expected[name].shape)} (feature_dim {feature_dim})")
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"model: tensor {name!r} of {path} has non-finite values")
    return Checkpoint({k: v.to(torch.float32) for k, v in tensors.items()}, feature_dim, heads, settings,
                      hashlib.sha256(data).hexdigest())


def _metadata(data: bytes) -> dict[str, str] | None:
    """The ``__metadata__`` of a safetensors file's JSON header (8-byte little-endian length first)."""
    if len(data) < 8:
        raise ValueError("shorter than the 8-byte header length")
    size = int.from_bytes(data[:8], "little")
    return json.loads(data[8: 8 + size].decode("utf-8")).get("__metadata__")


def apply_checkpoint(decoder: GaussianDecoder, checkpoint: Checkpoint) -> None:
    """Copy the checkpoint's parameters into ``decoder``; raises ValueError when its F_scene width
    differs from the decoder's."""
    if checkpoint.feature_dim != decoder.feature_dim:
        raise ValueError(f"model: the checkpoint's heads read {checkpoint.feature_dim} feature channels, the scene has "
                         f"feature_dim {decoder.feature_dim}")
    params = dict(decoder.named_parameters())
    with torch.no_grad():
        for name, tensor in checkpoint.tensors.items():
            params[name.removeprefix("decoder.")].copy_(tensor)


def resolve_model(model: str) -> Path | None:
    """The checkpoint file that the `SceneConfig.model` setting names: None for ``"none"`` (and for
    ``"default"`` while no checkpoint ships as the default), else a path."""
    if model == "none" or (model == "default" and SHIPPED_CHECKPOINT is None):
        return None
    return SHIPPED_FOLDER / SHIPPED_CHECKPOINT if model == "default" else Path(model).expanduser()


def load_model(decoder: GaussianDecoder, model: str) -> Checkpoint | None:
    """Load the `SceneConfig.model` setting into ``decoder`` (nothing for the training-free one);
    returns the checkpoint it loaded."""
    path = resolve_model(model)
    if path is None:
        return None
    checkpoint = load_checkpoint(path)
    apply_checkpoint(decoder, checkpoint)
    return checkpoint

