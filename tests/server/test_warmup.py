"""Start-up warm-up: after it, a fresh process has the kernels of every stage loaded, from depth codes to renders."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# numba kernels of each stage (a frame's 16-bit depth, fold, free space, undo record and roll-back, a decode (its SH fit)
# from scratch and one after a fold, render), and whether numba has loaded them.
PROBE = """
import canonical_core.datasets.depth_codes as depth_codes
import canonical_core.scene.hashing as hashing
import canonical_core.scene.kernels as fold
import canonical_core.scene.free_space as free_space
import canonical_core.scene.undo as undo
import canonical_core.scene.decoded as decoded
import canonical_core.scene.shapes as shapes
import canonical_core.scene.fields as fields
import canonical_core.rendering.cpu_tiles as tiles
import canonical_core.rendering.splat_geometry as geometry
import canonical_core.rendering.sh as sh
kernels = [fold.fold_kernel, hashing.resolve_kernel, hashing.remove_range_kernel, tiles.bin_splats_by_tile,
           geometry.project_numba, sh._sh_basis_kernel, sh._sh1_colour_kernel, depth_codes.metres_kernel]
kernels += [free_space._coarse_map_kernel, free_space.frustum_chunks_kernel, free_space.frame_free_space_kernel,
            free_space.history_free_space_kernel, free_space.update_chunk_boxes_kernel, undo._copy_chunks_kernel]
kernels += [shapes._voxel_shapes_kernel, decoded._gather_widened_kernel, fields._solve_sh_stored_kernel]
def loaded():
    return sum(bool(k.signatures) for k in kernels), len(kernels)
print(*loaded())
from server.warmup import warm_up
assert warm_up(num_threads=1) > 0
print(*loaded())
print([k.__name__ for k in kernels if not k.signatures])
"""


def test_warm_up_loads_the_kernels_of_every_stage_in_a_fresh_process():
    env = dict(os.environ, NUMBA_CACHE_DIR=os.environ.get("NUMBA_CACHE_DIR", str(REPO / ".numba_cache")))
    out = subprocess.run([sys.executable, "-c", PROBE], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    (before, total), (after, _) = (map(int, line.split()) for line in out.stdout.split("\n")[:2])
    assert before == 0 and total == 17
    assert after == total, out.stdout
