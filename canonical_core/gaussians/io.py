"""Gaussian export/import: the standard 3DGS PLY layout and antimatter15's 32-byte `.splat`.

PLY (binary little-endian, float32): ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2
rot_0..3`` with opacity as a logit, scales as logs and rotation as a (w, x, y, z) quaternion, which
is what common splat viewers read. ``f_rest_*`` is channel-major (all R coefficients, then G, then
B), as the reference 3DGS code writes it. After the 3DGS properties come extras that splat viewers
ignore: ``red green blue`` (uchar, the DC colour: what a point-cloud tool such as Open3D or MeshLab
shows) and the fused features and label scores as ``feat_*`` / ``label_*``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .container import GEOMETRY, Gaussians, check_finite, rgb_to_sh_dc, sh_dc_to_rgb

# the PLY specification's type names and the sized names other writers use
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "char": "i1", "int8": "i1",
              "uchar": "u1", "uint8": "u1", "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
              "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4"}
_OPACITY_EPS = 1e-6
MAX_LOG_SCALE = 88.0  # exp(88.7) is float32's largest value


def _dc_rgb8(g: Gaussians) -> np.ndarray:  # [N, 3] uint8: the colour seen head-on (SH degree 0)
    rgb = sh_dc_to_rgb(g.sh[:, 0].detach().cpu().float()).numpy()
    return np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)


def _ply_columns(g: Gaussians) -> dict[str, np.ndarray]:
    """Property name -> values (float32, or uint8 for the point-cloud colours), in header order."""
    n = len(g)
    k = g.sh.shape[1]
    sh = g.sh.detach().cpu().float().numpy()
    cols: dict[str, np.ndarray] = {}
    means = g.means.detach().cpu().float().numpy()
    for i, a in enumerate("xyz"):
        cols[a] = means[:, i]
    for a in ("nx", "ny", "nz"):
        cols[a] = np.zeros(n, np.float32)
    for c in range(3):
        cols[f"f_dc_{c}"] = sh[:, 0, c]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * (k - 1))  # channel-major, as 3DGS writes it
    for j in range(rest.shape[1]):
        cols[f"f_rest_{j}"] = rest[:, j]
    op = g.opacities.detach().cpu().double().numpy().clip(_OPACITY_EPS, 1 - _OPACITY_EPS)
    cols["opacity"] = np.log(op / (1 - op)).astype(np.float32)
    scales = np.log(g.scales.detach().cpu().double().numpy().clip(1e-12, None)).astype(np.float32)
    for i in range(3):
        cols[f"scale_{i}"] = scales[:, i]
    q = unit_quats(g.quats.detach().cpu().numpy())
    for i in range(4):
        cols[f"rot_{i}"] = q[:, i]
    rgb8 = _dc_rgb8(g)
    for i, a in enumerate(("red", "green", "blue")):
        cols[a] = rgb8[:, i]
    for prefix, t in (("feat", g.features), ("label", g.labels)):
        if t is not None:
            arr = t.detach().cpu().float().numpy()
            for j in range(arr.shape[1]):
                cols[f"{prefix}_{j}"] = arr[:, j]
    return cols


def unit_quats(q: np.ndarray) -> np.ndarray:  # [N, 4] -> [N, 4] float32
    """Rotations of unit length (a zero quaternion stays zero: the renderer draws it as a point). Trained
    3DGS files keep quaternions unnormalised, at any length; their norms are taken in float64, where
    float32's squares overflow from a length of about 1e19 (a rotation of zeros, or infinity)."""
    q64 = np.asarray(q, np.float64)
    return (q64 / np.linalg.norm(q64, axis=1, keepdims=True).clip(1e-300, None)).astype(np.float32)


def atomic_write(path: str | os.PathLike, payload: Iterable[bytes], sync_folder: bool = False) -> None:
    """``payload``'s chunks to ``path`` atomically: a temporary file beside it, fsync, rename, and with
    ``sync_folder`` an fsync of the folder (so the rename itself survives a crash). A failed write
    (``path`` a folder, a full disk, Ctrl-C) removes the temporary file, and its OSError names ``path``."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            for chunk in payload:
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.filename == str(tmp) and exc.errno is not None:
            raise type(exc)(exc.errno, exc.strerror, str(path)) from None  # the caller's path, not ours
        raise
    if sync_folder:
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)


class Encoded(NamedTuple):
    """A file of Gaussians as it is written a block of rows at a time (`ply_file`, `splat_file`): its
    size is known before any row is encoded (an HTTP answer's Content-Length), and each block is
    encoded as it is taken, so that the file's bytes never all sit in memory (a scene of millions of
    Gaussians makes a file of hundreds of MB, which an encode of the whole held several times over)."""

    size: int  # bytes of the whole file
    chunks: Iterator[bytes]  # the file's bytes: the header, then blocks of `ENCODE_ROWS` rows


ENCODE_ROWS = 1 << 14  # rows encoded at a time: a few MB of PLY, a few ms of work


def _rows(g: Gaussians, start: int, stop: int) -> Gaussians:
    return g.map(lambda t: t[start:stop])


def ply_file(g: Gaussians) -> Encoded:
    """The PLY file of ``g`` (header + binary body), a block of rows at a time; ValueError for a field
    with NaN or inf (`load_ply` would refuse the file)."""
    check_finite(g)
    layout = _ply_columns(_rows(g, 0, 0))  # the columns' names and types, from no rows
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(g)}"]
    header += [f"property {'uchar' if v.dtype == np.uint8 else 'float'} {name}" for name, v in layout.items()]
    head = ("\n".join(header + ["end_header"]) + "\n").encode("ascii")
    dtype = np.dtype([(name, "u1" if v.dtype == np.uint8 else "<f4") for name, v in layout.items()])

    def chunks() -> Iterator[bytes]:
        yield head
        for start in range(0, len(g), ENCODE_ROWS):
            cols = _ply_columns(_rows(g, start, start + ENCODE_ROWS))
            body = np.empty(len(cols["x"]), dtype)
            for name, values in cols.items():
                body[name] = values
            yield body.tobytes()

    return Encoded(len(head) + len(g) * dtype.itemsize, chunks())


def ply_bytes(g: Gaussians) -> bytes:
    """The PLY file as bytes (header + binary body)."""
    return b"".join(ply_file(g).chunks)


def save_ply(g: Gaussians, path: str | os.PathLike) -> None:
    """Write ``g`` in the standard 3DGS PLY layout (atomically: temp file, fsync, rename), a block
    of rows at a time."""
    atomic_write(path, ply_file(g).chunks)


def _parse_ply(data: bytes, name: str) -> dict[str, np.ndarray]:
    """The vertex properties of a binary little-endian PLY (``name``: the file, for the messages)."""
    end = re.search(rb"end_header\r?\n", data)  # a header written with Windows line ends too
    if not data.startswith(b"ply") or end is None:
        raise ValueError(f"{name}: not a PLY file (missing 'ply' magic or 'end_header')")
    lines = data[:end.start()].decode("ascii", errors="replace").splitlines()
    fmt, count, props, in_vertex = None, None, [], False
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            if len(parts) != 3:
                raise ValueError(f"{name}: malformed header line {line!r} (expected 'format <type> <version>')")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3:
                raise ValueError(f"{name}: malformed header line {line!r} (expected 'element <name> <count>')")
            if not parts[2].isdigit():  # digits alone: a negative count would read the whole body
                raise ValueError(f"{name}: element {parts[1]!r} has count {parts[2]!r}, expected a non-negative "
                                 "integer")
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                if count is not None:
                    raise ValueError(f"{name}: a second vertex element")
                count = int(parts[2])
            elif count is None and int(parts[2]) > 0:  # its rows would come first in the body
                raise ValueError(f"{name}: element {parts[1]!r} comes before the vertices; only files whose "
                                 "first element is vertex are read")
        elif parts[0] == "property" and in_vertex:
            if len(parts) >= 2 and (parts[1] == "list" or parts[1] not in _PLY_TYPES):
                raise ValueError(f"{name}: unsupported vertex property type {' '.join(parts[1:-1])!r}")
            if len(parts) != 3:
                raise ValueError(f"{name}: malformed header line {line!r} (expected 'property <type> <name>')")
            if parts[2] in dict(props):
                raise ValueError(f"{name}: vertex property {parts[2]!r} appears twice")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt != "binary_little_endian":
        raise ValueError(f"{name}: only binary_little_endian is supported, got {fmt!r}")
    if count is None:
        raise ValueError(f"{name}: no vertex element")
    dtype = np.dtype(props)
    body = data[end.end():]
    if len(body) < dtype.itemsize * count:
        raise ValueError(f"{name}: body holds {len(body)} bytes, expected {dtype.itemsize * count} for {count} "
                         "vertices")
    arr = np.frombuffer(body, dtype=dtype, count=count)
    return {prop: arr[prop].astype(np.float32) for prop in dtype.names}


def _stack(cols: dict[str, np.ndarray], prefix: str) -> np.ndarray | None:
    names = sorted((n for n in cols if n.startswith(prefix) and n[len(prefix):].isdigit()), key=lambda n: int(n[len(prefix):]))
    if not names:
        return None
    return np.stack([cols[n] for n in names], 1)


# every column of a Gaussian: a file without one would be read with a made-up value (a grey colour
# from f_dc_0 alone, a flat scale)
_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3")


def load_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS-layout PLY (as written by `save_ply` or 3DGS training code). Raises ValueError
    naming the file for one that is not such a PLY."""
    cols = _parse_ply(Path(path).read_bytes(), str(path))
    missing = [n for n in _REQUIRED if n not in cols]
    if missing:
        raise ValueError(f"{path}: missing 3DGS properties {missing}")
    if bad := [name for name, values in cols.items() if values.dtype.kind == "f" and not np.isfinite(values).all()]:
        raise ValueError(f"{path}: NaN or inf in the properties {bad}")  # every render would carry them
    n = len(cols["x"])
    rest = _stack(cols, "f_rest_")
    k = 1 + (0 if rest is None else rest.shape[1] // 3)
    if rest is not None and (rest.shape[1] % 3 or k not in (4, 9, 16)):
        raise ValueError(f"{path}: {rest.shape[1]} f_rest_* properties, expected 9, 24 or 45 (SH degree 1, 2 or 3)")
    sh = np.zeros((n, k, 3), np.float32)
    sh[:, 0] = np.stack([cols[f"f_dc_{c}"] for c in range(3)], 1)
    if rest is not None:
        sh[:, 1:] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    feats, labels = _stack(cols, "feat_"), _stack(cols, "label_")
    log_scales = np.stack([cols[f"scale_{i}"] for i in range(3)], 1)
    if (log_scales > MAX_LOG_SCALE).any():  # exp of it is inf in float32: a Gaussian no render draws
        raise ValueError(f"{path}: scale_* properties over {MAX_LOG_SCALE:g} (log scales: exp overflows float32)")
    return Gaussians(
        means=torch.from_numpy(np.stack([cols["x"], cols["y"], cols["z"]], 1)),
        scales=torch.from_numpy(np.exp(log_scales)),
        quats=torch.from_numpy(unit_quats(np.stack([cols[f"rot_{i}"] for i in range(4)], 1))),
        opacities=torch.sigmoid(torch.from_numpy(cols["opacity"])),
        sh=torch.from_numpy(sh),
        features=None if feats is None else torch.from_numpy(feats),
        labels=None if labels is None else torch.from_numpy(labels),
    )


SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def splat_file(g: Gaussians) -> Encoded:
    """antimatter15 `.splat`: 32 bytes per splat, most important (volume x opacity) first, a block of
    rows at a time; ValueError for NaN or inf in what it keeps."""
    check_finite(g, (*GEOMETRY, "sh"))
    # the order is the one array of the file's length (8 bytes a row of 32); its key is made in place
    importance = g.scales.detach().cpu().float().numpy().prod(1)
    importance *= g.opacities.detach().cpu().float().numpy()
    order = torch.from_numpy(np.argsort(np.negative(importance, out=importance), kind="stable"))
    del importance

    def chunks() -> Iterator[bytes]:
        for start in range(0, len(g), ENCODE_ROWS):
            rows = order[start:start + ENCODE_ROWS]  # the fields a .splat keeps, gathered (not the features)
            block = Gaussians(g.means[rows], g.scales[rows], g.quats[rows], g.opacities[rows], g.sh[rows, :1])
            rec = np.empty(len(block), SPLAT_DTYPE)
            rec["position"] = block.means.detach().cpu().float().numpy()
            rec["scale"] = block.scales.detach().cpu().float().numpy()
            rec["rgba"][:, :3] = _dc_rgb8(block)
            rec["rgba"][:, 3] = np.clip(np.round(block.opacities.detach().cpu().float().numpy() * 255), 0, 255)
            rec["rot"] = np.clip(np.round(unit_quats(block.quats.detach().cpu().numpy()) * 128 + 128), 0, 255)
            yield rec.tobytes()

    return Encoded(len(g) * SPLAT_DTYPE.itemsize, chunks())


def splat_bytes(g: Gaussians) -> bytes:
    """antimatter15 `.splat` as bytes (`splat_file`)."""
    return b"".join(splat_file(g).chunks)


def save_splat(g: Gaussians, path: str | os.PathLike) -> None:
    """Write the antimatter15 `.splat` layout (atomically). View-dependent SH is dropped (DC only)."""
    atomic_write(path, splat_file(g).chunks)


def load_splat(path: str | os.PathLike) -> Gaussians:
    """Read a `.splat` file (colours and rotations come back quantised to 8 bits)."""
    data = Path(path).read_bytes()
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(f"{path}: file size {len(data)} is not a multiple of 32 bytes (a .splat's rows)")
    rec = np.frombuffer(data, SPLAT_DTYPE)
    if bad := [name for name in ("position", "scale") if not np.isfinite(rec[name]).all()]:
        raise ValueError(f"{path}: NaN or inf in the {' and '.join(bad)} of its rows")
    rgba = rec["rgba"].astype(np.float32) / 255.0
    q = unit_quats((rec["rot"].astype(np.float32) - 128.0) / 128.0)

    return Gaussians(
        means=torch.from_numpy(rec["position"].copy()),
        scales=torch.from_numpy(rec["scale"].copy()),
        quats=torch.from_numpy(q),
        opacities=torch.from_numpy(rgba[:, 3].copy()),
        sh=rgb_to_sh_dc(torch.from_numpy(rgba[:, None, :3].copy())),
    )
