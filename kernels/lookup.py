"""Voxel -> band index lookup shared by the band, observation and ray-casting kernels.

The band's voxels are grouped by their 8^3 block (the same blocks as the TSDF):

* ``block_keys`` (B,) int64, sorted ascending: :func:`kernels.layout.block_key_np` of each
  block holding band voxels;
* ``block_table`` (B, 512) int32: band index of the voxel at local position
  ``(i % 8) * 64 + (j % 8) * 8 + (k % 8)`` of block ``b``, or -1 if that voxel is not in the band.

A lookup is a binary search over the blocks (log2 B steps, B ~ N / 100) plus one table read, with
no hashing races: :func:`band_index` is a pure read, deterministic and safe in any kernel.
"""

import numpy as np
import taichi as ti

from .funcs import block_row
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
