"""Reading snapshots (`scene.snapshot`): every failure to read one, whatever part of it is damaged, is a
ValueError naming the file (or "snapshot") and the problem, found before the scene allocates anything
of the size its header claims; a snapshot whose parts disagree with its header is not loaded."""

from __future__ import annotations

import io
import json
import re
import struct
import zipfile

import numpy as np
import pytest

from canonical_core import Frame, SceneConfig
from canonical_core.datasets import synthetic_rgbd
from canonical_core.scene import Scene
from canonical_core.scene.snapshot import read_config


@pytest.fixture(scope="module")
def snapshot() -> bytes:
    """A snapshot with every part: label sums, a frame waiting for depth, kept views, a colour solution."""
    frames = synthetic_rgbd(num_frames=3, width=64, height=48)
    scene = Scene(SceneConfig(voxel_size=0.02))
    for frame in frames[:2]:
        scene.fold(Frame(frame.rgb, frame.camera, frame.depth, labels=np.full((4, 4, 2), 0.5, np.float32)))
    assert scene.fold(Frame(frames[2].rgb, frames[2].camera)).pending
    scene.decode()
    assert scene._decoding.solution is not None and len(scene._keyframes)
    return scene.to_bytes()


def rewritten(data: bytes, edit) -> bytes:
    """``data`` with each member's array replaced by ``edit(name, array)`` (None: the member dropped)."""
    source, out = zipfile.ZipFile(io.BytesIO(data)), io.BytesIO()
    with zipfile.ZipFile(out, "w") as target:
        for name in source.namelist():
            array = edit(name[: -len(".npy")], np.load(io.BytesIO(source.read(name)), allow_pickle=False))
            if array is not None:
                buf = io.BytesIO()
                np.save(buf, array)
                target.writestr(name, buf.getvalue())
    return out.getvalue()


def member(name: str, change):
    return lambda n, a: change(a) if n == name else a


def header(**fields):
    def edit(name, array):
        if name != "header":
            return array
        return np.frombuffer(json.dumps(json.loads(array.tobytes()) | fields).encode(), np.uint8)
    return edit


def with_nan(array):
    array = array.copy()
    array.reshape(-1)[len(array.reshape(-1)) // 2] = np.nan
    return array


DAMAGES = {
    "keys missing": (member("state.keys", lambda a: None), r"state\.keys: missing"),
    "keys one short": (member("state.keys", lambda a: a[:-1]), r"header voxels: (\d+), but the state holds (\d+)"),
    "keys repeated": (member("state.keys", lambda a: np.concatenate([a[:1], a[:-1]])),
                      r"state\.keys: voxel keys appear more than once \(1 repeats"),
    "keys as floats": (member("state.keys", lambda a: a.astype(np.float64)),
                       r"state\.keys: expected int64 \[V\], got float64"),
    "NaN in a float16 mean": (member("state.f_mean", with_nan), r"state\.f_mean: holds NaN or inf"),
    "NaN in a float32 sum": (member("state.r_sum", with_nan), r"state\.r_sum: holds NaN or inf"),
    "a mean of another width": (member("state.f_mean", lambda a: a[:, :2]),
                                r"state\.f_mean: expected float16 \['V', 16\], got float16 \[\d+, 2\]"),
    "decoder weights of another shape": (member("decoder.opacity.u", lambda a: a[:1]),
                                         r"decoder\.opacity\.u: expected float \[8\], got float32 \[1\]"),
    "decoder weights missing": (member("decoder.opacity.u", lambda a: None),
                                r"an array is missing \(decoder\.opacity\.u"),
    "decoder weights NaN": (member("decoder.opacity.u", with_nan), r"decoder\.opacity\.u: holds NaN or inf"),
    "colour solution NaN": (member("colour_solution.offsets", with_nan), r"colour_solution\.offsets: holds NaN or inf"),
    "history missing": (member("history.threshold", lambda a: None), r"an array is missing \(history\.threshold\)"),
    "kept view missing": (member("keyframes.0.rgb", lambda a: None), r"an array is missing \(keyframes\.0\.rgb\)"),
    "header frames negative": (header(frames=-5), r"header frames: expected a non-negative integer, got -5"),
    "header frames fractional": (header(frames=1.5), r"header frames: expected a non-negative integer, got 1\.5"),
    "header voxels huge": (header(voxels=10**12), r"header voxels: 1000000000000, but the state holds \d+"),
    "header label_dim of another width": (header(label_dim=7),
                                          r"state\.label_mean: expected float16 \['V', 7\], got float16 \[\d+, 2\]"),
    "header label_dim without labels": (header(label_dim=0), r"state: expected the fields"),
    "header pending beyond the frames": (header(pending=3), r"an array is missing \(pending\.1\.rgb"),
    "header density NaN": (header(density=[float("nan"), 2]), r"header density: expected \[a finite sum"),
    "header config not a mapping": (header(config=None), r"header config: config: expected a mapping"),
    "header chosen a list": (header(chosen=[1]), r"header: expected mappings for chosen and model, got list"),
}


def test_an_undamaged_snapshot_loads_as_it_was_saved(snapshot):
    scene = Scene.from_bytes(snapshot)
    assert Scene.from_bytes(scene.to_bytes()).digest() == scene.digest() and len(scene._front.pending) == 1


@pytest.mark.parametrize("edit, message", DAMAGES.values(), ids=DAMAGES.keys())
def test_a_snapshot_that_disagrees_with_its_header_is_refused_naming_the_problem(snapshot, edit, message):
    with pytest.raises(ValueError, match=f"^snapshot: {message}"):
        Scene.from_bytes(rewritten(snapshot, edit))


def test_an_array_header_that_claims_more_data_than_its_member_holds_is_refused_before_it_is_allocated(snapshot):
    source, out = zipfile.ZipFile(io.BytesIO(snapshot)), io.BytesIO()
    with zipfile.ZipFile(out, "w") as target:
        for name in source.namelist():
            data = source.read(name)
            if name == "state.free.npy":  # a terabyte declared: numpy would allocate it before reading
                buf = io.BytesIO()
                np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False, "shape": (10**12,)})
                data = buf.getvalue() + data[-64:]
            target.writestr(name, data)
    with pytest.raises(ValueError, match=r"^snapshot: not a readable scene file \(state\.free\.npy: declares "
                                         r"4000000000000 bytes of data, holds 64\)"):
        Scene.from_bytes(out.getvalue())


def test_damaged_bytes_are_refused_naming_the_file(snapshot, tmp_path):
    info = zipfile.ZipFile(io.BytesIO(snapshot)).getinfo("history.weight.npy")
    name_length, extra_length = struct.unpack("<HH", snapshot[info.header_offset + 26: info.header_offset + 30])
    middle = info.header_offset + 30 + name_length + extra_length + info.compress_size // 2
    flipped = snapshot[:middle] + bytes([snapshot[middle] ^ 0xFF]) + snapshot[middle + 1:]  # its CRC fails
    for damaged in (flipped, snapshot[: len(snapshot) // 2], snapshot[:-10], b""):
        with pytest.raises(ValueError, match=r"^snapshot: not a readable scene file"):
            Scene.from_bytes(damaged)
        path = tmp_path / "scene.cgs"
        path.write_bytes(damaged)
        with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: not a readable scene file"):
            Scene.load(path)
    path.write_bytes(rewritten(snapshot, header(config={"voxel_size": "x"})))
    with pytest.raises(ValueError, match=f"^{re.escape(str(path))}: header config: voxel_size"):
        read_config(path)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n")  # an export given as a snapshot
    with pytest.raises(ValueError, match=r"not a readable scene file \(it starts with b'ply\\n', not as a snapshot's zip "
                                         r"archive does; a PLY file is read by load_ply\)$") as err:
        Scene.load(path)
    assert "pickle" not in str(err.value)  # numpy's own message pointed at an unsafe option


def test_anything_but_bytes_is_refused_naming_the_argument():
    for data in ("abc", None, [1, 2]):
        with pytest.raises(ValueError, match=f"^data: expected the bytes of a snapshot, got {type(data).__name__}"):
            Scene.from_bytes(data)
