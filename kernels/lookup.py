"""Voxel -> band index lookup shared by the band, observation and ray-casting kernels.

The band's voxels are grouped by their 8^3 block (the same blocks as the TSDF):

* ``block_keys`` (B,) int64, sorted ascending: :func:`block_key` of each block holding band voxels;
* ``block_table`` (B, 512) int32: band index of the voxel at local position
  ``(i % 8) * 64 + (j % 8) * 8 + (k % 8)`` of block ``b``, or -1 if that voxel is not in the band.

A lookup is a binary search over the blocks (log2 B steps, B ~ N / 100) plus one table read, with
no hashing races: :func:`band_index` is a pure read, deterministic and safe in any kernel.
"""

import numpy as np
import taichi as ti

BLOCK = 8
KEY_BIAS = 1 << 20  # block coordinates in [-2^20, 2^20) (8.4M voxels per axis)


def block_key_np(blocks: np.ndarray) -> np.ndarray:
    """int64 key of integer block coordinates (..., 3); ascending keys = lexicographic blocks."""
    b = np.asarray(blocks, dtype=np.int64) + KEY_BIAS
    return (b[..., 0] << 42) | (b[..., 1] << 21) | b[..., 2]


def build_block_table(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(block_keys, block_table)`` for band voxels ``ijk`` (N, 3) int32 (band index = row)."""
    ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
    blocks = np.floor_divide(ijk, BLOCK)
    keys, inverse = np.unique(block_key_np(blocks), return_inverse=True)
    local = ijk - blocks * BLOCK
    table = np.full((len(keys), BLOCK ** 3), -1, dtype=np.int32)
    table[inverse.reshape(-1), local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]] = np.arange(
        len(ijk), dtype=np.int32)
    return keys.astype(np.int64), table


@ti.func
def block_key(bi: ti.i64, bj: ti.i64, bk: ti.i64) -> ti.i64:
    return ((bi + KEY_BIAS) << 42) | ((bj + KEY_BIAS) << 21) | (bk + KEY_BIAS)


@ti.func
def find_block(keys: ti.template(), key: ti.i64) -> ti.i32:
    """Row of ``key`` in the sorted block keys, or -1 (binary search, read only)."""
    lo, hi = 0, keys.shape[0]
    while lo < hi:  # first position with keys[pos] >= key
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    out = -1
    if lo < keys.shape[0] and keys[lo] == key:
        out = lo
    return out


@ti.func
def band_index(block_keys: ti.template(), block_table: ti.template(), i: ti.i32, j: ti.i32,
               k: ti.i32) -> ti.i32:
    """Band index of voxel (i, j, k), or -1. ``block_keys``/``block_table`` are ndarray kernel
    arguments as described in the module docstring. Deterministic (read only)."""
    bi, bj, bk = i // BLOCK, j // BLOCK, k // BLOCK  # Taichi's // floors for negative ints
    row = find_block(block_keys, block_key(ti.cast(bi, ti.i64), ti.cast(bj, ti.i64),
                                           ti.cast(bk, ti.i64)))
    out = -1
    if row >= 0:
        out = block_table[row, (i - bi * BLOCK) * 64 + (j - bj * BLOCK) * 8 + (k - bk * BLOCK)]
    return out
