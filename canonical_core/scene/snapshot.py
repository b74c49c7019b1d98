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

import contextlib
import io
import json
import math
import os
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np
import torch

from ..evidence import DepthConsistency
from ..config import SceneConfig
from ..frame import MAX_LABEL_CHANNELS
from ..gaussians.io import atomic_write
from .decoding import ColourSolution
from .fields import unpack_keys
from .free_space import SeeThroughHistory
from .keyframes import Keyframes
from .voxel_map import ARRAYS

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "copied_parts", "encode", "encode_snapshot", "from_bytes", "load",
           "model_arrays", "read_config", "reduce", "save", "snapshot_parts", "state_arrays"]

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
    the decoder's parameters the snapshot holds. Raises ValueError naming ``data`` for anything but
    bytes, and naming the snapshot for bytes that are not a readable snapshot: another format, an
    unsupported version, a damaged file, or contents that do not agree with its header."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ValueError(f"data: expected the bytes of a snapshot, got {type(data).__name__}")
    return _read(scene_type, data, "snapshot")


def reduce(scene: Scene) -> tuple:
    """`Scene.__reduce__`: a pickled or deep-copied scene (a process pool's or a Ray task's argument)
    is rebuilt from its snapshot, so the copy has its digest and folds on alike; the undo records are
    not carried (the copy cannot `rollback` what the original folded), nor `keep_frames`."""
    return (type(scene).from_bytes, (scene.to_bytes(),))


def load(scene_type: type[Scene], path: str | os.PathLike) -> Scene:
    """The scene the snapshot file ``path`` holds (`Scene.load`, ``scene_type`` its class; see `from_bytes`):
    ValueError naming the file for one that is not a readable snapshot (OSError for a missing one)."""
    return _read(scene_type, Path(path).read_bytes(), str(path))


def read_config(path: str | os.PathLike) -> SceneConfig:
    """The settings the snapshot file ``path`` was made with, from its header alone (no array is read).
    Raises ValueError naming the file as `load` does."""
    with _reading(str(path)):
        npz, header = _opened(path)
        npz.close()
        return _config(header)


@contextlib.contextmanager
def _reading(name: str):
    """Every failure to read a snapshot as a ValueError naming ``name`` (the file, or "snapshot"): a
    damaged file fails anywhere in the readers of its parts (zip CRC, truncated or missing arrays,
    values a part refuses), each with an exception of its own."""
    try:
        yield
    except MemoryError:  # a scene too large for this machine: the file is not at fault
        raise
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    except KeyError as exc:
        raise ValueError(f"{name}: an array is missing ({exc.args[0] if exc.args else exc})") from None
    except Exception as exc:  # noqa: BLE001 - a damaged file fails in any reader, each with its own type
        raise ValueError(f"{name}: not a readable scene file ({type(exc).__name__}: {exc})") from None


def _read(scene_type: type[Scene], data: bytes, name: str) -> Scene:
    with _reading(name):
        npz, header = _opened(data)
        with npz:
            return _scene_of(scene_type, npz, header)


def _scene_of(scene_type: type[Scene], npz, header: dict) -> Scene:
    """The scene of an opened snapshot, its header and arrays checked against each other before the
    scene allocates anything of their size."""
    config = _config(header)
    frames, voxels, pending = (_count(header, field) for field in ("frames", "voxels", "pending"))
    label_dim = _count(header, "label_dim")
    if label_dim > MAX_LABEL_CHANNELS:
        raise ValueError(f"header label_dim: expected at most {MAX_LABEL_CHANNELS}, got {label_dim}")
    density_sum, density_frames = _density(header)
    chosen, model = header.get("chosen"), header.get("model")
    if not isinstance(chosen, (dict, type(None))) or not isinstance(model, (dict, type(None))):
        raise ValueError(f"header: expected mappings for chosen and model, got {type(chosen).__name__} and "
                         f"{type(model).__name__}")
    state = _prefixed(npz, "state")
    _check_state(state, voxels)
    # the decoder's parameters come from the snapshot, not from the model file (which may be gone)
    scene = scene_type(config, initial_capacity=max(voxels, 16), load_model=False)
    scene.model_sha256 = (model or {}).get("sha256")
    scene.chosen = dict(chosen or scene.chosen)  # why the settings are what they are (`choices`)
    if label_dim:
        scene._voxels.set_label_dim(label_dim)
    if header["version"] == FORMAT_VERSION:  # earlier versions hold other fields, converted on loading
        _check_layout(state, scene._voxels.sums())
    scene._voxels.load_sums(_local_representatives(state, scene.config.voxel_size))
    scene.frames = frames
    scene._density_sum, scene._density_frames = density_sum, density_frames
    scene._history = SeeThroughHistory.from_arrays(scene.config.free_space.history, _prefixed(npz, "history"))
    scene._front.load_arrays(npz, pending)
    scene._consistency = DepthConsistency.from_arrays(_prefixed(npz, "consistency"))
    scene._keyframes = Keyframes.from_arrays(scene.config.colour_solve.views, scene.config.colour_solve.scale,
                                             _prefixed(npz, "keyframes"))
    for prefix, module in (("decoder", scene.decoder), ("appearance", scene.appearance)):
        module.load_state_dict(_parameters(npz, prefix, module.state_dict()))
    if "colour_solution.rows" in npz.files:
        solution = _prefixed(npz, "colour_solution")
        _check_finite(solution, "colour_solution")
        scene._decoding.solution = ColourSolution.from_arrays(solution)
    return scene


def _opened(source) -> tuple:
    """(the npz, its header) of a snapshot's bytes or file; ValueError for one that is not a snapshot,
    another format or an unsupported version. The arrays are read when they are indexed."""
    in_memory = isinstance(source, (bytes, bytearray, memoryview))
    npz = None
    try:
        try:
            size = memoryview(source).nbytes if in_memory else os.path.getsize(source)
            if in_memory:
                magic = bytes(memoryview(source)[:4])
            else:
                with open(source, "rb") as f:
                    magic = f.read(4)
            if magic != ZIP_MAGIC:  # numpy would try other formats, and name its pickle option for them
                raise ValueError(f"it starts with {magic!r}, not as a snapshot's zip archive does"
                                 + ("; a PLY file is read by load_ply" if magic[:3] == b"ply" else ""))
            npz = np.load(io.BytesIO(source) if in_memory else source, allow_pickle=False)
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise ValueError(f"a single {type(npz).__name__}, not an archive of arrays")
            _check_sizes(npz, size)
            header = json.loads(npz["header"].tobytes().decode())
        except Exception as exc:  # any decoding failure means "not one of our snapshots"
            raise ValueError(f"not a readable scene file ({exc})") from None
        if not isinstance(header, dict):
            raise ValueError(f"not a readable scene file (its header is a {type(header).__name__}, not a mapping)")
        if header.get("format") != FORMAT_NAME:
            raise ValueError(f"unknown format {header.get('format')!r}")
        if header.get("version") not in READABLE_VERSIONS:
            raise ValueError(f"version {header.get('version')} is not supported (expected one of "
                             f"{READABLE_VERSIONS})")
    except BaseException:
        if isinstance(npz, np.lib.npyio.NpzFile):
            npz.close()  # a file it opened
        raise
    return npz, header


ZIP_MAGIC = b"PK\x03\x04"  # a snapshot is an .npz: a zip archive of arrays

# deflate's largest expansion: a member that claims to unpack to more is damaged
MAX_DEFLATE_RATIO = 1032


def _check_sizes(npz, size: int) -> None:
    """Refuse a member whose sizes cannot be true of a file of ``size`` bytes, or whose array header
    declares more data than the member holds: numpy allocates the declared shape before it reads, so
    a damaged header could ask for any amount of memory."""
    for info in npz.zip.infolist():
        ratio = 1 if info.compress_type == zipfile.ZIP_STORED else MAX_DEFLATE_RATIO
        if info.compress_size > size or info.file_size > ratio * info.compress_size:
            raise ValueError(f"{info.filename}: sizes {info.compress_size} / {info.file_size} bytes do not fit a "
                             f"file of {size} bytes")
        if not info.filename.endswith(".npy"):
            continue
        with npz.zip.open(info) as member:
            version = np.lib.format.read_magic(member)
            read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
            if version not in read_header:
                raise ValueError(f"{info.filename}: unsupported array format {version}")
            shape, _, dtype = read_header[version](member)
            declared = math.prod(shape) * dtype.itemsize
            if declared > info.file_size - member.tell():
                raise ValueError(f"{info.filename}: declares {declared} bytes of data, holds "
                                 f"{info.file_size - member.tell()}")


def _config(header: dict) -> SceneConfig:
    try:
        return SceneConfig.from_dict(header.get("config"))
    except ValueError as exc:
        raise ValueError(f"header config: {exc}") from None


def _count(header: dict, field: str) -> int:
    """A count of the header (``pending`` may be absent: files before it had none waiting)."""
    value = header.get(field, 0 if field == "pending" else None)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"header {field}: expected a non-negative integer, got {value!r}")
    return value


def _density(header: dict) -> tuple[float, int]:
    """The header's observation density (summed density, frames it sums over); files before it hold none."""
    density = header.get("density", [0.0, 0])
    if (not isinstance(density, list) or len(density) != 2 or isinstance(density[0], bool)
            or not isinstance(density[0], (int, float)) or not 0 <= density[0] < math.inf
            or isinstance(density[1], bool) or not isinstance(density[1], int) or density[1] < 0):
        raise ValueError(f"header density: expected [a finite sum >= 0, a frame count >= 0], got {density!r}")
    return float(density[0]), density[1]


def _check_state(state: dict[str, np.ndarray], voxels: int) -> None:
    """The fused state's arrays against the header's voxel count (every array a row per voxel), the
    per-voxel arrays every version holds (`voxel_map.ARRAYS`) against their dtypes, its float arrays
    finite and its voxel keys distinct (a key twice would be two voxels at one place)."""
    for field, (dtype, shape) in ARRAYS.items():
        if field not in state:
            raise ValueError(f"state.{field}: missing")
        if state[field].dtype != dtype or state[field].ndim != 1 + len(shape) or state[field].shape[1:] != shape:
            raise ValueError(f"state.{field}: expected {np.dtype(dtype)} [V{''.join(f', {n}' for n in shape)}], got "
                             f"{state[field].dtype} {list(state[field].shape)}")
    if len(state["keys"]) != voxels:
        raise ValueError(f"header voxels: {voxels}, but the state holds {len(state['keys'])} (state.keys)")
    for field, array in state.items():
        if array.ndim < 1 or len(array) != voxels:
            raise ValueError(f"state.{field}: expected a row for each of the header's {voxels} voxels, got shape "
                             f"{list(array.shape)}")
    _check_finite(state, "state")
    keys = np.sort(state["keys"])
    repeated = np.flatnonzero(keys[1:] == keys[:-1])
    if len(repeated):
        raise ValueError(f"state.keys: voxel keys appear more than once ({len(repeated)} repeats, the first of key "
                         f"{keys[repeated[0]]})")


def _check_layout(state: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    """The state's arrays against those of the scene's own map (``expected``, its empty sums): the
    same fields, each of the same dtype and row shape."""
    if state.keys() != expected.keys():
        raise ValueError(f"state: expected the fields {sorted(expected)}, got {sorted(state)}")
    for field, array in expected.items():
        if state[field].dtype != array.dtype or state[field].shape[1:] != array.shape[1:]:
            raise ValueError(f"state.{field}: expected {array.dtype} {['V', *array.shape[1:]]}, got "
                             f"{state[field].dtype} {list(state[field].shape)}")


def _check_finite(arrays: dict[str, np.ndarray], prefix: str) -> None:
    """Refuse NaN or inf in the float arrays of ``arrays``: every decode would carry it."""
    for field, array in arrays.items():
        if array.dtype.kind == "f" and not _finite(array):
            raise ValueError(f"{prefix}.{field}: holds NaN or inf")


def _finite(array: np.ndarray) -> bool:
    half = array.dtype == np.float16
    # float16 (most of the state) by its bits, an exponent of all ones being inf or NaN: integer
    # operations, several times faster than numpy's isfinite of float16
    flat = array.reshape(-1).view(np.uint16) if half else array.reshape(-1)
    step = 1 << 22  # a bounded temporary, however large the state
    for i in range(0, flat.size, step):
        part = flat[i: i + step]
        finite = (part & 0x7C00).max() != 0x7C00 if half else np.isfinite(part).all()
        if not finite:
            return False
    return True


def _parameters(npz, prefix: str, expected: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The snapshot's parameters of the module ``prefix`` (``expected``: its state dict), each of its shape."""
    params = {k: npz[f"{prefix}.{k}"] for k in expected}
    for k, array in params.items():
        if array.dtype.kind != "f" or array.shape != tuple(expected[k].shape):
            raise ValueError(f"{prefix}.{k}: expected float {list(expected[k].shape)}, got {array.dtype} "
                             f"{list(array.shape)}")
    _check_finite(params, prefix)
    return {k: torch.from_numpy(array.copy()) for k, array in params.items()}


def _local_representatives(sums: dict[str, np.ndarray], voxel_size: float | None) -> dict[str, np.ndarray]:
    """``sums`` with the representatives' positions in local voxel units, as a fold keeps them: files
    before version 6 hold them as world positions (``rep_pos``)."""
    if "rep_local" in sums or "rep_pos" not in sums or not len(sums["rep_pos"]):
        return sums
    cells = unpack_keys(torch.from_numpy(np.asarray(sums["keys"], np.int64))).numpy()
    local = np.asarray(sums["rep_pos"], np.float32) * np.float32(1.0 / voxel_size) - (cells + 0.5).astype(np.float32)
    return sums | {"rep_pos": local}


class _Part(dict):
    """The arrays of one part of a snapshot, by the rest of their names; a missing one is named in full."""

    def __init__(self, prefix: str, arrays: dict[str, np.ndarray]):
        super().__init__(arrays)
        self.prefix = prefix

    def __missing__(self, key):
        raise KeyError(f"{self.prefix}.{key}")


def _prefixed(npz, prefix: str) -> dict[str, np.ndarray]:
    """The arrays of ``npz`` (a loaded snapshot) named ``prefix.*``, by the rest of their names."""
    return _Part(prefix, {k[len(prefix) + 1:]: npz[k] for k in npz.files if k.startswith(f"{prefix}.")})
