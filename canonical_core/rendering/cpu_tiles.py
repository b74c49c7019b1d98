"""Fast CPU backend: numba projection and tile binning, then per-tile compositing in C (float32,
no autograd).

Same image model and arithmetic as the reference: the splat geometry comes from the same source
(`splat_geometry`) and the per-pixel expressions are written alike, so the two agree to float
rounding (the transmittance is a float32 product here and the reference's float64 cumprod: they
differ by about 1e-7 over the tens of layers a pixel blends).
The compositor (`_composite.c`) is vectorised across pixels, which numba did not manage; the numba
kernels are compiled with ``cache=True``: set NUMBA_CACHE_DIR (the Makefile does) to keep their
machine code across processes.
"""

from __future__ import annotations

import ctypes
import importlib.util
from typing import NamedTuple, Sequence

import numba
import numpy as np
import torch
from torch import Tensor

from ..camera import Camera
from ..gaussians import Gaussians
from .projection import Blend, Channel, channel_values, world_to_camera
from .sh import sh_to_rgb_fast
from .splat_geometry import SPLAT_RECORD, TILE_SIZE, project_numba, slope_bounds

# The compositor's builds (setup.py), baseline first.
_BUILDS = ("_composite", "_composite_x86_64_v3")


TILE_SHIFT = TILE_SIZE.bit_length() - 1  # a pixel's tile is pixel >> TILE_SHIFT (floor division, cheaper)
assert TILE_SIZE == 1 << TILE_SHIFT


@numba.njit(parallel=True, cache=True)
def bin_splats_by_tile(
    boxes: np.ndarray,  # [N, 4] int32 pixel boxes (u_lo, u_hi, v_lo, v_hi); empty where lo > hi
    tiles_x: int,
    num_tiles: int,
    num_chunks: int,
) -> tuple[np.ndarray, np.ndarray]:  # tile_starts [T + 1] int64, splat_ids [K] int32
    """Counting sort of (tile, splat) pairs by tile; each tile lists its splats in input order.

    Each of ``num_chunks`` parallel tasks counts and fills one contiguous run of splats; runs are
    laid out in order within every tile, which keeps the input order.
    """
    n = boxes.shape[0]
    chunk = -(-n // num_chunks)
    cursors = np.zeros((num_chunks, num_tiles), np.int64)
    for k in numba.prange(num_chunks):
        cursor = cursors[k]
        for i in range(k * chunk, min(n, (k + 1) * chunk)):
            if boxes[i, 0] <= boxes[i, 1]:
                x0, x1 = boxes[i, 0] >> TILE_SHIFT, boxes[i, 1] >> TILE_SHIFT
                for ty in range(boxes[i, 2] >> TILE_SHIFT, (boxes[i, 3] >> TILE_SHIFT) + 1):
                    for tile in range(ty * tiles_x + x0, ty * tiles_x + x1 + 1):
                        cursor[tile] += 1
    tile_starts = np.empty(num_tiles + 1, np.int64)
    total = 0
    for tile in range(num_tiles):
        tile_starts[tile] = total
        for k in range(num_chunks):
            count = cursors[k, tile]
            cursors[k, tile] = total
            total += count
    tile_starts[num_tiles] = total
    splat_ids = np.empty(total, np.int32)
    for k in numba.prange(num_chunks):
        cursor = cursors[k]
        for i in range(k * chunk, min(n, (k + 1) * chunk)):
            if boxes[i, 0] <= boxes[i, 1]:
                x0, x1 = boxes[i, 0] >> TILE_SHIFT, boxes[i, 1] >> TILE_SHIFT
                for ty in range(boxes[i, 2] >> TILE_SHIFT, (boxes[i, 3] >> TILE_SHIFT) + 1):
                    for tile in range(ty * tiles_x + x0, ty * tiles_x + x1 + 1):
                        splat_ids[cursor[tile]] = i
                        cursor[tile] += 1
    return tile_starts, splat_ids


def compositor_builds() -> dict[str, str]:
    """The compositor's builds present in this installation: {build name: path of its library}."""
    builds = {}
    for name in _BUILDS:
        spec = importlib.util.find_spec(f"{__package__}.{name}")
        if spec is not None and spec.origin is not None:
            builds[name] = spec.origin
    return builds


def load_compositor(name: str) -> ctypes.CDLL:
    """Load one build of the compositor (a name from ``compositor_builds()``), its functions typed."""
    library = ctypes.CDLL(compositor_builds()[name])
    pointer, size = ctypes.c_void_p, ctypes.c_int64
    library.canonical_composite_job.argtypes = [pointer, size, pointer, pointer, size, pointer, size, pointer, size] + [
        size, size, size, size, pointer, pointer, pointer, pointer, pointer
    ]
    library.canonical_composite_job.restype = size
    library.canonical_weights_job.argtypes = [pointer, size, pointer, pointer, size, pointer, size, size, size, size,
                                              ctypes.c_float, pointer, pointer, pointer, pointer, pointer,
                                              pointer, size, size, pointer, pointer, pointer]
    library.canonical_weights_job.restype = size
    library.canonical_job_work.argtypes = [size]  # a job's address, as numba passes it
    library.canonical_job_work.restype = None
    library.canonical_job_finish.argtypes = [size]
    library.canonical_job_finish.restype = ctypes.c_int
    library.canonical_stable_depth_order.argtypes = [pointer, size, pointer]
    library.canonical_stable_depth_order.restype = ctypes.c_int
    library.canonical_cpu_has_x86_64_v3.argtypes = []
    library.canonical_cpu_has_x86_64_v3.restype = ctypes.c_int
    return library


@numba.njit(parallel=True, nogil=True, cache=True)
def _work_on_numba_threads(work, job, num_threads):  # work: the library's canonical_job_work
    for _ in numba.prange(num_threads):
        work(job)


def _run_job(library: ctypes.CDLL, job: int, num_threads: int, name: str) -> None:
    """Work ``job`` on ``num_threads`` of numba's threads, then free it.

    The compositor starts no threads of its own: numba's OpenMP threads, which have just run the
    projection and the binning, would spin idle for a while after those (OpenMP's wait policy)
    against any other thread on the same cores, so they take the tiles instead."""
    if not job:
        raise MemoryError(f"{name}: out of memory for the job")
    previous_threads = numba.get_num_threads()
    numba.set_num_threads(max(1, min(num_threads, numba.config.NUMBA_NUM_THREADS)))
    try:
        _work_on_numba_threads(library.canonical_job_work, job, numba.get_num_threads())
    finally:
        numba.set_num_threads(previous_threads)
        status = library.canonical_job_finish(job)
    if status:
        raise MemoryError(f"{name}: out of memory for the per-thread tile buffers")


def _default_build() -> str:
    """The x86-64-v3 build where it is built and the CPU runs it, else the baseline one."""
    builds = compositor_builds()
    if _BUILDS[0] not in builds:
        raise ImportError(
            f"{__package__}: the compositor library {_BUILDS[0]} is not built; "
            "reinstall the package (pip install -e .) with a C compiler (gcc) present"
        )
    faster = _BUILDS[1] in builds and load_compositor(_BUILDS[0]).canonical_cpu_has_x86_64_v3()
    return _BUILDS[1] if faster else _BUILDS[0]


compositor_build = _default_build()
_compositor = load_compositor(compositor_build)


def _address(array: np.ndarray, dtype: type, name: str) -> int:
    if array.dtype != dtype or not array.flags.c_contiguous:
        raise ValueError(f"{name}: expected a C-contiguous {np.dtype(dtype)} array, got {array.dtype}")
    return array.ctypes.data


def _rows(array: np.ndarray, dtype: type, name: str) -> tuple[int, int]:
    """Address and row stride (in elements) of a 2-D array of contiguous rows, such as a view of
    some columns of a wider array."""
    item = np.dtype(dtype).itemsize
    if array.dtype == dtype and array.ndim == 2 and array.size == 0:
        return array.ctypes.data, 0
    if array.dtype != dtype or array.ndim != 2 or array.strides[0] % item or (array.shape[1] > 1 and array.strides[1] != item):
        raise ValueError(f"{name}: expected 2-D {np.dtype(dtype)} rows of contiguous elements, got {array.dtype} "
                         f"{list(array.shape)} with strides {list(array.strides)}")
    return array.ctypes.data, array.strides[0] // item


def stable_depth_order(depths: np.ndarray) -> np.ndarray:  # [n] float32 > 0 -> [n] int32 permutation
    """Stable ascending order of positive depths, as the compositor sorts each tile's splats:
    equal depths keep input order."""
    order = np.empty(depths.shape[0], np.int32)
    if _compositor.canonical_stable_depth_order(_address(depths, np.float32, "depths"), depths.shape[0],
                                                _address(order, np.int32, "order")):  # fmt: skip
        raise MemoryError("stable_depth_order: out of memory")
    return order


def composite_tiles(
    tile_starts: np.ndarray,  # [T + 1] int64
    splat_ids: np.ndarray,  # [K] int32, per tile in input order
    splats: np.ndarray,  # [N, SPLAT_RECORD] float32 records from project_numba (rows may be strided)
    boxes: np.ndarray,  # [N, 4] int32 (rows may be strided)
    values: np.ndarray,  # [N, D] float32 (rows may be strided)
    tiles_x: int,
    out_values: np.ndarray,  # [H, W, D] float32
    out_depth_sums: np.ndarray,  # [H, W] float32
    out_weight_sums: np.ndarray,  # [H, W] float32
    out_transmittance: np.ndarray,  # [H, W] float32
    out_median_depth: np.ndarray | None,  # [H, W] float32, 0 where the transmittance never falls below 1/2; None: skip
    num_threads: int,
    compositor: ctypes.CDLL | None = None,  # a build from load_compositor; default: compositor_build
) -> None:
    """Blend each tile's splats front to back (the C library, on ``num_threads`` threads that take
    tiles one at a time: tiles differ a lot in work). Splat-outer within the tile: each splat visits
    the 8-pixel blocks of its box's rows; every pixel still sees the splats in depth order. Each
    pixel's median depth is the depth of the splat at which its transmittance first falls below 1/2."""
    height, width, num_channels = out_values.shape
    if splats.shape[1] != SPLAT_RECORD:
        raise ValueError(f"splats: expected [N, {SPLAT_RECORD}] records, got {list(splats.shape)}")
    library = compositor or _compositor
    job = library.canonical_composite_job(
        _address(tile_starts, np.int64, "tile_starts"), tile_starts.shape[0] - 1,
        _address(splat_ids, np.int32, "splat_ids"), *_rows(splats, np.float32, "splats"),
        *_rows(boxes, np.int32, "boxes"), *_rows(values, np.float32, "values"), num_channels,
        tiles_x, width, height, _address(out_values, np.float32, "out_values"),
        _address(out_depth_sums, np.float32, "out_depth_sums"),
        _address(out_weight_sums, np.float32, "out_weight_sums"),
        _address(out_transmittance, np.float32, "out_transmittance"),
        None if out_median_depth is None else _address(out_median_depth, np.float32, "out_median_depth"),
    )  # fmt: skip
    _run_job(library, job, num_threads, "composite_tiles")


def composite_weights(
    tile_starts: np.ndarray,  # [T + 1] int64
    splat_ids: np.ndarray,  # [K] int32, per tile in input order
    splats: np.ndarray,  # [N, SPLAT_RECORD] float32 records from project_numba (rows may be strided)
    boxes: np.ndarray,  # [N, 4] int32 (rows may be strided)
    tiles_x: int,
    width: int,
    height: int,
    min_weight: float,
    slot_starts: np.ndarray,  # [T] int64 where each tile's entries go (room for each splat's box pixels in it)
    out_pixels: np.ndarray,  # [B] int32 written: v * width + u
    out_ids: np.ndarray,  # [B] int32 written: the splat (record) index
    out_weights: np.ndarray,  # [B] float32 written: alpha T, at least min_weight
    out_counts: np.ndarray,  # [T] int64 written: entries of each tile
    num_threads: int,
    blend: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    # with ``blend``: (values [N, D] float32, rows may be strided; out_values [H, W, D], out_weight_sums [H, W],
    # out_transmittance [H, W] float32, written as `composite_tiles` writes them)
) -> None:
    """The compositor's weights mode: each tile blended as `composite_tiles` blends it, but instead
    of sums, every (pixel, splat) weight alpha T >= ``min_weight`` written out in blend order (a
    splat's pixels row by row, splats front to back). With ``blend``, the same pass also writes the
    sums of ``values`` as `composite_tiles` does, every weight in (the same numbers, bit for bit)."""
    if splats.shape[1] != SPLAT_RECORD:
        raise ValueError(f"splats: expected [N, {SPLAT_RECORD}] records, got {list(splats.shape)}")
    values, out_values, out_weight_sums, out_transmittance = blend if blend is not None else (None,) * 4
    sums = (None, 0, 0, None, None, None) if blend is None else (
        *_rows(values, np.float32, "values"), values.shape[1], _address(out_values, np.float32, "out_values"),
        _address(out_weight_sums, np.float32, "out_weight_sums"), _address(out_transmittance, np.float32, "out_transmittance"))
    job = _compositor.canonical_weights_job(
        _address(tile_starts, np.int64, "tile_starts"), tile_starts.shape[0] - 1,
        _address(splat_ids, np.int32, "splat_ids"), *_rows(splats, np.float32, "splats"),
        *_rows(boxes, np.int32, "boxes"), tiles_x, width, height, min_weight,
        _address(slot_starts, np.int64, "slot_starts"), _address(out_pixels, np.int32, "out_pixels"),
        _address(out_ids, np.int32, "out_ids"), _address(out_weights, np.float32, "out_weights"),
        _address(out_counts, np.int64, "out_counts"), *sums,
    )  # fmt: skip
    _run_job(_compositor, job, num_threads, "composite_weights")


def _float32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)


# A splat's line: its record, its pixel box (int32) and room for up to LINE_VALUES channel values,
# 16 float32 columns, 64 bytes on a 64-byte boundary: a tile's gather of a splat reads one cache
# line, where three arrays cost a cache miss each (the scene's order is random in screen space).
LINE = 16
LINE_VALUES = LINE - SPLAT_RECORD - 4


class SplatLines(NamedTuple):
    """Views of one line per Gaussian (`LINE`), in input order."""

    records: np.ndarray  # [N, SPLAT_RECORD] float32 splat records (zero where culled)
    boxes: np.ndarray  # [N, 4] int32 pixel boxes, empty (lo > hi) where culled
    spare: np.ndarray  # [N, LINE_VALUES] float32, unwritten: room for the channel values


def project_records(
    gaussians: Gaussians,
    camera: Camera,
    near_plane: float,
) -> SplatLines:
    """`project_numba` on float32 CPU copies of ``gaussians``: every Gaussian's splat record and
    pixel box (empty, lo > hi, where it is culled), in input order, in one line per splat."""
    f32, n = np.float32, len(gaussians)
    width, height = camera.width, camera.height
    view = tuple(f32(v) for v in world_to_camera(camera, torch.float32, torch.device("cpu"))[:3].reshape(-1).tolist())
    block = np.empty(n * LINE + LINE, f32)  # project_numba writes every record and box
    first = (-block.ctypes.data % 64) // block.itemsize
    lines = block[first: first + n * LINE].reshape(n, LINE)
    records, boxes = lines[:, :SPLAT_RECORD], lines.view(np.int32)[:, SPLAT_RECORD: SPLAT_RECORD + 4]
    project_numba(
        _float32(gaussians.means), _float32(gaussians.quats), _float32(gaussians.scales), _float32(gaussians.opacities),
        view, (f32(camera.fx), f32(camera.fy), f32(camera.cx), f32(camera.cy)),
        tuple(f32(s) for s in slope_bounds(camera.fx, camera.fy, camera.cx, camera.cy, width, height)),
        f32(near_plane), width, height, records, boxes,
    )  # fmt: skip
    return SplatLines(records, boxes, lines[:, SPLAT_RECORD + 4:])


def render_cpu(
    gaussians: Gaussians,
    camera: Camera,
    channels: Sequence[Channel],
    near_plane: float,
    num_threads: int,
    compositor: ctypes.CDLL | None = None,  # a build from load_compositor; default: compositor_build
    median_depth: bool = False,
) -> Blend:
    """Project and composite on ``num_threads`` threads; returns CPU float32 tensors (the median
    depth only with ``median_depth``: its test costs the blend a few percent)."""

    gaussians = gaussians.detach().to("cpu", torch.float32)
    width, height = camera.width, camera.height
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    f32 = np.float32
    out_depth_sums, out_weight_sums = np.zeros((height, width), f32), np.zeros((height, width), f32)
    out_transmittance = np.ones((height, width), f32)
    out_median_depth = np.zeros((height, width), f32) if median_depth else None
    num_threads = min(num_threads, numba.config.NUMBA_NUM_THREADS)  # at most one thread a core
    previous_threads = numba.get_num_threads()
    numba.set_num_threads(num_threads)
    try:
        splats, boxes, spare = project_records(gaussians, camera, near_plane)
        if tuple(channels) == ("rgb",):  # the colours straight into the splats' lines
            values = spare[:, :3]
            sh_to_rgb_fast(gaussians.sh, gaussians.means, camera.c2w64()[:3, 3].astype(f32), out=values)
        else:
            values = _float32(channel_values(gaussians, camera, channels, colour=sh_to_rgb_fast))
            if values.shape[1] <= LINE_VALUES:
                spare[:, : values.shape[1]] = values
                values = spare[:, : values.shape[1]]
        out_values = np.zeros((height, width, values.shape[1]), f32)
        tile_starts, splat_ids = bin_splats_by_tile(boxes, tiles_x, tiles_x * tiles_y, numba.get_num_threads())
        composite_tiles(
            tile_starts, splat_ids, splats, boxes, values, tiles_x,
            out_values, out_depth_sums, out_weight_sums, out_transmittance, out_median_depth, num_threads, compositor,
        )  # fmt: skip
    finally:
        numba.set_num_threads(previous_threads)
    maps = (out_values, out_depth_sums, out_weight_sums, out_transmittance)
    return Blend(*(torch.from_numpy(a) for a in maps), None if out_median_depth is None else torch.from_numpy(out_median_depth))
