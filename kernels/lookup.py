"""Voxel -> band index lookup shared by the band, observation and ray-casting kernels.

The band's voxels are grouped by their 8^3 block (the same blocks as the TSDF):

* ``block_keys`` (B,) int64, sorted ascending: :func:`kernels.layout.block_key_np` of each
  block holding band voxels;
* ``block_table`` (B, 512) int32: band index of the voxel at local position
  ``(i % 8) * 64 + (j % 8) * 8 + (k % 8)`` of block ``b``, or -1 if that voxel is not in the band.

A lookup is a binary search over the blocks (log2 B steps, B ~ N / 100) plus one table read:
:func:`band_index` is a pure read, deterministic and safe in any kernel. The observation kernels
of :mod:`kernels.dataterm` find a block through a hash table of the keys instead
(:func:`build_block_hash`, built once by numpy, read only: no races either), and
:func:`look_up_sample` finds the 8 corners of a sample's cell through a block cache per image
row and sample index, so that most samples need no lookup at all.
"""

import numpy as np
import taichi as ti

from .funcs import (block_key, block_row, cell_corners, corner_offset, floor_i32,
                    reaches_block, trilinear)
from .layout import BLOCK, BLOCK_VOXELS, block_key_np, decode_keys


def build_block_table(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(block_keys, block_table)`` for band voxels ``ijk`` (N, 3) int32 (band index = row)."""
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    blocks = np.floor_divide(ijk, BLOCK)
    keys, inverse = np.unique(block_key_np(blocks), return_inverse=True)
    local = ijk - blocks * BLOCK
    table = np.full((len(keys), BLOCK_VOXELS), -1, dtype=np.int32)
    table[inverse.reshape(-1), local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]] = np.arange(
        len(ijk), dtype=np.int32)
    return keys.astype(np.int64), table


@ti.func
def band_index(block_keys: ti.template(), block_table: ti.template(), i: ti.i32, j: ti.i32,
               k: ti.i32) -> ti.i32:
    """Band index of voxel (i, j, k), or -1. ``block_keys``/``block_table`` are ndarray kernel
    arguments as described in the module docstring. Deterministic (read only)."""
    bi, bj, bk = i // BLOCK, j // BLOCK, k // BLOCK  # Taichi's // floors for negative ints
    row = block_row(block_keys, bi, bj, bk)
    out = -1
    if row >= 0:
        out = block_table[row, (i - bi * BLOCK) * 64 + (j - bj * BLOCK) * 8 + (k - bk * BLOCK)]
    return out


HASH_MULTIPLIER = 0x9E3779B97F4A7C15  # 2^64 / golden ratio: Fibonacci hashing of the keys


def build_block_hash(block_keys: np.ndarray) -> np.ndarray:
    """The block keys as an open-addressing hash table, for :func:`hashed_block_row` (an O(1)
    lookup where :func:`kernels.funcs.block_row` searches). (2 + 2P,) int64: ``[0]`` =
    ``log2 P``, then slot s at ``[2 + 2s]`` (a key, -1 where empty) and ``[3 + 2s]`` (its row
    in the block table); ``P`` the power of two >= 2 B (at most half full). A key goes to slot
    ``(key * HASH_MULTIPLIER mod 2^64) >> (64 - log2 P)``, or the next free one after it
    (linear probing, wrapping around): in rounds, every key not yet placed tries its next slot
    and, where several try one free slot, the smallest key takes it. A key then sits behind
    occupied slots only, so a probe from its home slot reaches it before an empty one. The
    same table every time."""
    keys = np.asarray(block_keys, np.int64).ravel()
    bits = max(1, int(2 * len(keys) - 1).bit_length())
    size = 1 << bits
    slot_key = np.full(size, -1, np.int64)
    slot_row = np.zeros(size, np.int64)
    pos = ((keys.astype(np.uint64) * np.uint64(HASH_MULTIPLIER))
           >> np.uint64(64 - bits)).astype(np.int64)
    pending = np.argsort(keys, kind="stable")  # rows in key order: the smaller key first
    while len(pending):
        cand = pos[pending]
        free = slot_key[cand] == -1
        slots, first = np.unique(cand[free], return_index=True)
        won = pending[free][first]
        slot_key[slots], slot_row[slots] = keys[won], won
        pending = pending[~np.isin(pending, won)]
        pos[pending] = (pos[pending] + 1) & (size - 1)
    table = np.empty(2 + 2 * size, np.int64)
    table[0], table[1] = bits, 0
    table[2::2], table[3::2] = slot_key, slot_row
    return table


@ti.func
def hashed_block_row(block_hash: ti.template(), bi: ti.i32, bj: ti.i32, bk: ti.i32) -> ti.i32:
    """Row of block (bi, bj, bk) in the block table, or -1: :func:`kernels.funcs.block_row`
    through :func:`build_block_hash`'s table (read only)."""
    key = block_key(ti.cast(bi, ti.i64), ti.cast(bj, ti.i64), ti.cast(bk, ti.i64))
    bits = ti.cast(block_hash[0], ti.u64)
    mask = (ti.i32(1) << ti.cast(bits, ti.i32)) - 1
    s = ti.cast((ti.cast(key, ti.u64) * ti.u64(HASH_MULTIPLIER)) >> (ti.u64(64) - bits), ti.i32)
    row = -1
    while block_hash[2 + 2 * s] != -1:  # at most half full: an empty slot ends every probe
        if block_hash[2 + 2 * s] == key:
            row = ti.cast(block_hash[3 + 2 * s], ti.i32)
            break
        s = (s + 1) & mask
    return row


def band_ijk_from_table(block_keys: np.ndarray, block_table: np.ndarray,
                        n_voxels: int) -> np.ndarray:
    """Invert :func:`build_block_table`: voxel ``ijk`` (N, 3) int32 of every band index
    0..N-1. Raises ValueError unless the table holds each index exactly once."""
    keys = np.asarray(block_keys, np.int64)
    table = np.asarray(block_table, np.int32)
    rows, t = np.nonzero(table >= 0)
    idx = table[rows, t].astype(np.int64)
    if len(idx) != n_voxels or (len(idx) and (idx.min() < 0 or idx.max() >= n_voxels
                                              or np.bincount(idx, minlength=n_voxels).max() != 1)):
        raise ValueError(f"block table does not hold band indices 0..{n_voxels - 1} exactly once "
                         f"({len(idx)} entries)")
    blocks = decode_keys(keys[rows])
    local = np.stack([t >> 6, (t >> 3) & 7, t & 7], axis=1)
    ijk = np.empty((n_voxels, 3), np.int32)
    ijk[idx] = blocks * BLOCK + local
    return ijk


SAMPLE_DROPPED, SAMPLE_ACCEPTED, SAMPLE_GATED = 0, 1, 2  # what look_up_sample finds
UNSEARCHED = -2  # block cache: row not looked up yet (-1: looked up, not in the band)
BLOCK_CACHE = 11  # block cache entry of a sample: its block (3), the rows of the 8 it reaches


@ti.func
def look_up_sample(slot: ti.i32, first: ti.i32, z: ti.f64, o, m_ray, y: ti.f64,
                   gate: ti.f64, block_hash: ti.template(),
                   block_table: ti.template(), ref: ti.template(), scratch: ti.template(),
                   blocks: ti.template()) -> ti.i32:
    """A sample (depth ``z`` > 0, distance ``y`` from its pixel's surface) in its pixel row's
    ``slot`` (row ``vs``, sample ``j``: ``vs (mf + m + 1) + j + mf``; ``first``: j = -mf): its
    cell's corners (band indices) into ``scratch[8 slot ..]``, corner 7 -1 where one is outside
    the band, -2 where the side gate drops it (kernels.observe, steps 3 and 3b), through the
    row's block cache ``blocks[BLOCK_CACHE slot ..]``. ``scratch`` and ``blocks`` are flat
    ((rows, samples, 8) and (rows, samples, BLOCK_CACHE) int32: a flat index is computed once,
    where a 3-d one reloaded the shape after every store). Returns SAMPLE_ACCEPTED,
    SAMPLE_DROPPED or SAMPLE_GATED."""
    c0 = floor_i32(o + z * m_ray)
    b = ti.Vector([c0[0] // BLOCK, c0[1] // BLOCK, c0[2] // BLOCK])
    # block cache per sample index j: sample j of the next pixels in the row is mostly in the
    # same block (8 voxels = many pixels); else sample j - 1's entry, which this ray mostly
    # just filled. Block b + s (s in {0, 1}^3) is searched only when a cell first reaches it,
    # from b's last voxel layer along s's axes (UNSEARCHED till then)
    e = slot * BLOCK_CACHE
    if (b != ti.Vector([blocks[e + t] for t in ti.static(range(3))])).any():
        ep = ti.select(first, e, e - BLOCK_CACHE)  # sample j - 1's entry (when j > -mf)
        prev = ti.Vector([blocks[ep + t] for t in ti.static(range(3))])
        same = not first and (b == prev).all()
        for t in ti.static(range(3)):
            blocks[e + t] = b[t]
        for t in ti.static(range(3, BLOCK_CACHE)):
            blocks[e + t] = ti.select(same, blocks[ep + t], UNSEARCHED)
    for t in range(8):
        if reaches_block(c0, b, t) and blocks[e + 3 + t] == UNSEARCHED:
            nb = b + corner_offset(t)
            blocks[e + 3 + t] = hashed_block_row(block_hash, nb[0], nb[1], nb[2])
    idx = cell_corners(block_table, c0, b, ti.Vector(
        [blocks[e + 3 + t] for t in ti.static(range(8))]))
    gated = 0
    if idx[7] >= 0 and gate > 0:
        # step 3b: the reference SDF interpolated at the sample must not put it on the other
        # side of the surface by more than the gate
        g = o + z * m_ray
        a = trilinear(g - ti.cast(c0, ti.f64))
        t_ref = ti.f64(0.0)
        for c in ti.static(range(8)):
            t_ref += a[c] * ti.cast(ref[idx[c]], ti.f64)
        # NaN (a corner without reference) fails both tests: kept
        if (y < 0 and t_ref > gate) or (y > 0 and t_ref < -gate):
            gated = 1
    for c in ti.static(range(8)):
        scratch[slot * 8 + c] = idx[c]
    status = SAMPLE_DROPPED
    if gated:
        scratch[slot * 8 + 7] = -2
        status = SAMPLE_GATED
    elif idx[7] >= 0:
        status = SAMPLE_ACCEPTED
    return status
