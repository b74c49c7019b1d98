"""The voxel lattice's keys and the open-addressing hash table that maps them to voxel indices
(numba kernels): keys of points, insert, remove and lookup, and the grouping of one frame's
observations by voxel (`resolve_kernel`), which the fold (`kernels.fold_kernel`) then folds.

Layout: voxel keys pack (i, j, k) + KEY_OFFSET into 21 bits each; ``table`` holds voxel indices
(-1 = empty) and the key is read back from ``keys[index]``, so the table costs 4 bytes a slot.
"""

from __future__ import annotations

import numba
import numpy as np

from ..config import KEY_BITS, KEY_OFFSET

_KEY_LIMIT = 1 << KEY_BITS
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(inline="always")
def home_slot(key, mask):
    h = np.uint64(key) * _HASH_MULT
    return np.int64((h >> np.uint64(29)) & np.uint64(mask))


@numba.njit(inline="always")
def find_voxel(table, keys, key, mask):
    """Index of ``key`` (>= 0), or -1 - slot of the empty slot where it would go."""
    s = home_slot(key, mask)
    while True:
        idx = table[s]
        if idx < 0:
            return -1 - s
        if keys[idx] == key:
            return idx
        s = (s + 1) & mask


@numba.njit(inline="always")
def _voxel_coord(x, inv_voxel):
    return np.int64(np.floor(x * inv_voxel))


@numba.njit(inline="always")
def _pack(i, j, k):
    a, b, c = i + KEY_OFFSET, j + KEY_OFFSET, k + KEY_OFFSET
    if a < 0 or b < 0 or c < 0 or a >= _KEY_LIMIT or b >= _KEY_LIMIT or c >= _KEY_LIMIT:
        return np.int64(-1)
    return (a << (2 * KEY_BITS)) | (b << KEY_BITS) | c


@numba.njit(cache=True, parallel=True)
def voxel_keys_kernel(points, inv_voxel, out):
    """Keys of the voxels holding ``points`` ([M, 3] float32); -1 outside the lattice."""
    for i in numba.prange(points.shape[0]):
        out[i] = _pack(_voxel_coord(points[i, 0], inv_voxel), _voxel_coord(points[i, 1], inv_voxel),
                       _voxel_coord(points[i, 2], inv_voxel))


@numba.njit(cache=True)
def insert_range_kernel(table, keys, start, stop):
    """Enter voxels ``start`` .. ``stop - 1`` into ``table`` (their keys are not in it yet)."""
    mask = table.shape[0] - 1
    for idx in range(start, stop):
        table[-1 - find_voxel(table, keys, keys[idx], mask)] = idx


@numba.njit(cache=True)
def remove_range_kernel(table, keys, start, stop):
    """Take voxels ``stop - 1`` down to ``start`` out of ``table`` (each present), the last entered
    first, by backward-shift deletion: an entry after the hole moves into it when its home slot lies
    outside (hole, entry], so no probe chain is cut. In a table filled in index order (as the map fills
    it), removing the last entered first leaves it exactly as entering voxels [0, start) alone would,
    slot for slot: no entry after a hole has its home before it, so nothing moves."""
    mask = table.shape[0] - 1
    for idx in range(stop - 1, start - 1, -1):
        hole = home_slot(keys[idx], mask)
        while table[hole] != idx:  # its slot (`find_voxel` gives the entry, not where it is)
            hole = (hole + 1) & mask
        j = hole
        while True:
            j = (j + 1) & mask
            e = table[j]
            if e < 0:
                break
            home = home_slot(keys[e], mask)
            if (home <= hole or home > j) if hole < j else (home <= hole and home > j):
                table[hole] = e
                hole = j
        table[hole] = -1


@numba.njit(cache=True)
def lookup_kernel(table, keys, query, out):
    """out[i] = the voxel index of ``query[i]``, -1 where it is absent. Probes at most the whole
    table, so a lookup in a full table (never made by the map, whose load stays below 1) ends too."""
    mask = table.shape[0] - 1
    for i in range(query.shape[0]):
        s = home_slot(query[i], mask)
        out[i] = -1
        for _ in range(table.shape[0]):
            idx = table[s]
            if idx < 0:
                break
            if keys[idx] == query[i]:
                out[i] = idx
                break
            s = (s + 1) & mask


@numba.njit(inline="always")
def _group_range(obs_keys, rel, uses_rel, lo, hi, table, frame_keys, head, tail, best, next_obs):
    """Group observations [lo, hi) by key, as if they were the whole frame (`resolve_kernel`): slots
    in first-occurrence order (frame_keys, head, tail, best: views whose slot 0 is this range's
    first), chains through next_obs, deduped in ``table`` (all -1). Returns (slots, observations
    inside the lattice)."""
    mask = table.shape[0] - 1
    n_slots = 0
    n_obs = 0
    last_key, last_t = np.int64(-1), -1
    for i in range(lo, hi):
        key = obs_keys[i]
        if key < 0:
            continue
        n_obs += 1
        next_obs[i] = -1
        # neighbouring pixels of a row mostly fall in one voxel: skip the probe for a repeat
        t = last_t if key == last_key else find_voxel(table, frame_keys, key, mask)
        last_key = key
        if t >= 0:
            last_t = t
            next_obs[tail[t]] = i
            tail[t] = i
            if uses_rel and rel[i] > rel[best[t]]:
                best[t] = i
            continue
        t = n_slots
        last_t = t
        n_slots += 1
        table[-1 - find_voxel(table, frame_keys, key, mask)] = t
        frame_keys[t] = key
        head[t] = tail[t] = best[t] = i
    return n_slots, n_obs


@numba.njit(cache=True, parallel=True)
def resolve_kernel(obs_keys, rel, uses_rel, table, keys, parts, tables,
                   frame_keys, touched, new_keys, best, head, tail, next_obs):
    """Phase A (reads the scene, writes only scratch): group the frame's observations by voxel.

    Each distinct key of the frame gets a slot t (first-occurrence order; keys < 0, outside the
    lattice, get none): touched[t] = the voxel's index, or -2 - j for the j-th key not yet in the
    scene (new_keys[j]); best[t] = the slot's most reliable observation (first maximum wins, as in
    the batch rule). The slot's observations form a chain in frame order: head[t], next_obs[i]
    (-1 ends it; tail is scratch).

    The observations are grouped in ``parts`` contiguous ranges at once (one per thread), each in a
    hash table of its own, so that the scene's large, cache-cold table is probed once per voxel, not
    per pixel. The ranges' slots are then merged in order: a key seen in an earlier range keeps that
    slot, its chain goes on with this range's, and its best changes only for a strictly more reliable
    observation. That is what one pass over the frame gives, for any number of parts. ``tables``
    holds the ranges' tables and the merge's (`resolve_tables_size` entries at least); it is scratch
    reused from frame to frame, so that no fold faults in fresh pages for them.
    Returns (slots, new keys, observations inside the lattice).
    """
    m = obs_keys.shape[0]
    parts = max(1, min(parts, m))
    bounds = np.empty(parts + 1, np.int64)
    for p in range(parts + 1):
        bounds[p] = p * m // parts
    slots = np.zeros(parts, np.int64)
    counted = np.zeros(parts, np.int64)
    size = _table_size((m + parts - 1) // parts)  # no range holds more observations than this
    for p in numba.prange(parts):
        lo, hi = bounds[p], bounds[p + 1]
        local = tables[p * size: p * size + _table_size(hi - lo)]
        local[:] = -1
        slots[p], counted[p] = _group_range(obs_keys, rel, uses_rel, lo, hi, local, frame_keys[lo:], head[lo:],
                                            tail[lo:], best[lo:], next_obs)
    # merge the parts' slots (part p's slot s sits at bounds[p] + s) into one numbering, in order
    n_touched = slots[0]
    merged = tables[parts * size: parts * size + _table_size(slots.sum())]
    merged[:] = -1
    merged_mask = merged.shape[0] - 1
    for t in range(n_touched):
        merged[-1 - find_voxel(merged, frame_keys, frame_keys[t], merged_mask)] = t
    for p in range(1, parts):
        for s in range(slots[p]):
            j = bounds[p] + s
            key = frame_keys[j]
            t = find_voxel(merged, frame_keys, key, merged_mask)
            if t >= 0:  # seen earlier in the frame: this part's chain goes on from that slot's
                next_obs[tail[t]] = head[j]
                tail[t] = tail[j]
                if uses_rel and rel[best[j]] > rel[best[t]]:
                    best[t] = best[j]
                continue
            free = -1 - t
            t = n_touched  # <= j: the slot written is one this loop has read already, or this one
            n_touched += 1
            frame_keys[t], head[t], tail[t], best[t] = key, head[j], tail[j], best[j]
            merged[free] = t
    # the scene's table is probed once per distinct key, in parallel (the probes are cache misses)
    mask = table.shape[0] - 1
    for t in numba.prange(n_touched):
        touched[t] = find_voxel(table, keys, frame_keys[t], mask)
    n_new = 0
    for t in range(n_touched):  # new voxels are numbered in first-occurrence order
        if touched[t] < 0:
            new_keys[n_new] = frame_keys[t]
            touched[t] = -2 - n_new
            n_new += 1
    return n_touched, n_new, counted.sum()


@numba.njit(inline="always")
def _table_size(n):
    """A power of two at least twice ``n`` (a hash table of n keys stays at most half full)."""
    size = 1
    while size < 2 * n:
        size *= 2
    return size


def resolve_tables_size(m: int, parts: int) -> int:
    """Entries of `resolve_kernel`'s ``tables`` for ``m`` observations in ``parts`` ranges: each range's
    table (a power of two under four times the largest range) and the merge's (under four times m)."""
    parts = max(1, min(parts, m))
    return parts * 4 * (-(-m // parts)) + 4 * m + 2
