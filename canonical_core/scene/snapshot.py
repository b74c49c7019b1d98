"""Scene snapshots: a scene's whole state as one self-contained, versioned file, and back.

A snapshot is an .npz with a JSON header: the fused state (sums, free-space history, the depth
front end's source window and waiting frames, the colour solve's kept views and last solution) and
the decoder's and appearance module's parameters, so it decodes without the model file it came
from. It round-trips the fused state bit for bit (equal `Scene.digest`), which is what lets a
re-fold start from a checkpoint (`refold`) and a service resume a session from disk.

The functions read and write the scene's parts; `Scene` holds its lock around the ones that read
the live state (see each).
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np
import torch

from ..evidence import DepthConsistency
from ..config import SceneConfig
from ..gaussians.io import atomic_write
from .decoding import ColourSolution
from .fields import unpack_keys
from .free_space import SeeThroughHistory
from .keyframes import Keyframes

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "copied_parts", "encode", "encode_snapshot", "from_bytes", "load",
           "model_arrays", "read_config", "save", "snapshot_parts", "state_arrays"]

FORMAT_NAME = "canonicalgs-scene"
# 4 adds the per-view observation density (v3 files load with a density of 1); 5 stores the records
# as the map does (`stored`: the feature sum as a float16 mean; v3 and v4 files hold float32
# sums, stored on loading as a fold stores them); 6 stores the colour and position moments and the SH
# sums in float16 too, as means and central moments, the representative's position in local voxel
# units and its feature as its 8-bit direction (v5 files hold float32 sums and world positions); 7
# stores the label scores' sums in float16 too, as means (v6 files hold them as float32 sums)
FORMAT_VERSION = 7
READABLE_VERSIONS = (3, 4, 5, 6, FORMAT_VERSION)


def state_arrays(scene: Scene, sums: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Every array of the fused state: sums (``sums``, else copies of them), free-space history,
    source window, waiting frames, the colour solve's kept views. The caller holds the scene's lock."""
    arrays = {f"state.{k}": v for k, v in (scene.sums() if sums is None else sums).items()}
    arrays |= {f"history.{k}": v for k, v in scene._history.to_arrays().items()}
    arrays |= scene._front.to_arrays()
    if scene._keyframes.capacity:  # scenes without the colour solve keep their earlier digests
        arrays |= {f"keyframes.{k}": v for k, v in scene._keyframes.to_arrays().items()}
    return arrays


def snapshot_parts(scene: Scene, sums: dict[str, np.ndarray] | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """The snapshot's header and arrays but the model's (`model_arrays`), the arrays views of the
    live state but ``sums``; the caller holds the scene's lock."""
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "config": scene.config.to_dict(),
              "frames": scene.frames, "label_dim": scene.label_dim, "voxels": len(scene),
              "pending": len(scene._front.pending), "density": [scene._density_sum, scene._density_frames],
              "model": {"setting": scene.config.model, "sha256": scene.model_sha256}, "chosen": scene.chosen}
    arrays = state_arrays(scene, sums) | {f"consistency.{k}": v for k, v in scene._consistency.to_arrays().items()}
    solution = scene._decoding.solution
    if solution is not None:  # not in the digest: decodes made it of the state, and they may differ in when
        arrays |= {f"colour_solution.{k}": v for k, v in solution.to_arrays().items()}
    return header, arrays


def copied_parts(scene: Scene) -> tuple[dict, dict[str, np.ndarray]]:
    """`Scene.snapshot_parts`, for a caller that holds the scene's lock: every array a copy."""
    # the sums as views into one block copy of the records (a copy per field would read every
    # record once per field); the encoding makes them contiguous off the lock, to the same bytes
    header, arrays = snapshot_parts(scene, scene._voxels.sums_of(scene._voxels.copied_state()))
    # the rest (history, source window, kept views) are views of the live state: copied
    arrays = {k: v if k.startswith("state.") else np.array(v, copy=True) for k, v in arrays.items()}
    return header, arrays | model_arrays(scene)


def encode_snapshot(header: dict, arrays: dict[str, np.ndarray], out: BinaryIO | None = None) -> bytes | None:
    """The snapshot's bytes (an .npz with a JSON header) of `Scene.snapshot_parts`; with ``out`` (a
    binary file) written there instead of returned, with no copy of the whole in memory."""
    buf = io.BytesIO() if out is None else out
    np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
    return buf.getvalue() if out is None else None


def encode(scene: Scene, header: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """The snapshot's bytes of `snapshot_parts` of ``scene``, its model's parameters added."""
    return encode_snapshot(header, arrays | model_arrays(scene))


def model_arrays(scene: Scene) -> dict[str, np.ndarray]:
    """The decoder's and the appearance module's parameters, as snapshot arrays (copies)."""
    return {f"{prefix}.{k}": v.detach().cpu().numpy().copy()
            for prefix, module in (("decoder", scene.decoder), ("appearance", scene.appearance))
            for k, v in module.state_dict().items()}


def save(scene: Scene, path: str | os.PathLike) -> None:
    """`Scene.save`: ``scene.to_bytes()`` written atomically (temp file, fsync, rename, fsync of the
    folder: `atomic_write`, which leaves no temporary file when the write fails)."""
    atomic_write(path, [scene.to_bytes()], sync_folder=True)


def from_bytes(scene_type: type[Scene], data: bytes) -> Scene:
    """The scene a `Scene.to_bytes` snapshot holds (`Scene.from_bytes`, ``scene_type`` its class), with
    the decoder's parameters the snapshot holds. Raises ValueError for bytes that are not a snapshot, another
    format or an unsupported version."""
    npz, header = _opened(io.BytesIO(data))
    # the decoder's parameters come from the snapshot, not from the model file (which may be gone)
    scene = scene_type(SceneConfig.from_dict(header["config"]), initial_capacity=max(int(header["voxels"]), 16),
                       load_model=False)
    scene.model_sha256 = (header.get("model") or {}).get("sha256")
    scene.chosen = dict(header.get("chosen") or scene.chosen)  # why the settings are what they are (`choices`)
    if header["label_dim"]:
        scene._voxels.set_label_dim(int(header["label_dim"]))
    scene._voxels.load_sums(_local_representatives(_prefixed(npz, "state"), scene.config.voxel_size))
    scene.frames = int(header["frames"])
    density_sum, density_frames = header.get("density", [0.0, 0])
    scene._density_sum, scene._density_frames = float(density_sum), int(density_frames)
    scene._history = SeeThroughHistory.from_arrays(scene.config.free_space.history, _prefixed(npz, "history"))
    scene._front.load_arrays(npz, int(header.get("pending", 0)))
    scene._consistency = DepthConsistency.from_arrays(_prefixed(npz, "consistency"))
    scene._keyframes = Keyframes.from_arrays(scene.config.colour_solve.views, scene.config.colour_solve.scale,
                                             _prefixed(npz, "keyframes"))
    for prefix, module in (("decoder", scene.decoder), ("appearance", scene.appearance)):
        module.load_state_dict({k: torch.from_numpy(npz[f"{prefix}.{k}"].copy()) for k in module.state_dict()})
    if "colour_solution.rows" in npz.files:
        scene._decoding.solution = ColourSolution.from_arrays(_prefixed(npz, "colour_solution"))
    return scene


def _opened(source) -> tuple:
    """(the npz, its header) of a snapshot file or buffer; ValueError for one that is not a snapshot,
    another format or an unsupported version. The arrays are read when they are indexed."""
    try:
        npz = np.load(source, allow_pickle=False)
        header = json.loads(npz["header"].tobytes().decode())
    except Exception as exc:  # any decoding failure means "not one of our snapshots"
        raise ValueError(f"snapshot: not a readable scene file ({exc})") from None
    if header.get("format") != FORMAT_NAME:
        raise ValueError(f"snapshot: unknown format {header.get('format')!r}")
    if header.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"snapshot: version {header.get('version')} is not supported (expected one of {READABLE_VERSIONS})")
    return npz, header


def read_config(path: str | os.PathLike) -> SceneConfig:
    """The settings the snapshot file ``path`` was made with, from its header alone (no array is read).
    Raises ValueError as `from_bytes` does."""
    npz, header = _opened(path)
    npz.close()
    return SceneConfig.from_dict(header["config"])


def load(scene_type: type[Scene], path: str | os.PathLike) -> Scene:
    """The scene the snapshot file ``path`` holds (`Scene.load`, ``scene_type`` its class; see `from_bytes`)."""
    return scene_type.from_bytes(Path(path).read_bytes())


def _local_representatives(sums: dict[str, np.ndarray], voxel_size: float | None) -> dict[str, np.ndarray]:
    """``sums`` with the representatives' positions in local voxel units, as a fold keeps them: files
    before version 6 hold them as world positions (``rep_pos``)."""
    if "rep_local" in sums or "rep_pos" not in sums or not len(sums["rep_pos"]):
        return sums
    cells = unpack_keys(torch.from_numpy(np.asarray(sums["keys"], np.int64))).numpy()
    local = np.asarray(sums["rep_pos"], np.float32) * np.float32(1.0 / voxel_size) - (cells + 0.5).astype(np.float32)
    return sums | {"rep_pos": local}


def _prefixed(npz, prefix: str) -> dict[str, np.ndarray]:
    """The arrays of ``npz`` (a loaded snapshot) named ``prefix.*``, by the rest of their names."""
    return {k[len(prefix) + 1:]: npz[k] for k in npz.files if k.startswith(f"{prefix}.")}
