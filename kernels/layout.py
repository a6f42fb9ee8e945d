"""Constants of the voxel layout that several kernels share, and the block-key packing.

numpy only (no Taichi): host code outside ``kernels`` (bftaichi, tools) may use it without
initialising a backend. The Taichi side of the packing, :func:`kernels.funcs.block_key`, uses
the same constants.

Blocks. Voxels are grouped in blocks of ``BLOCK^3`` voxels (the TSDF's blocks and the band
lookup's): block index ``b = floor(ijk / BLOCK)``, local voxel ``(a, b_, c) = ijk - BLOCK b``
at position ``64 a + 8 b_ + c`` of the block (``BLOCK_VOXELS`` positions).

Block keys. A block ``b`` in ``[-KEY_BIAS, KEY_BIAS)^3`` packs into one int64,
``KEY_BITS = 21`` bits per axis: ``b0 + KEY_BIAS`` in bits 42..62, ``b1 + KEY_BIAS`` in bits
21..41, ``b2 + KEY_BIAS`` in bits 0..20 (:func:`block_key_np`). Ascending keys are
lexicographic blocks, and inside the range keys are linear in the coordinates:
``key(b + d) = key(b) + key_step(d)`` (:func:`block_key_steps`).

Stencil. The 27 offsets ``{-1, 0, 1}^3`` of a voxel's neighbours are numbered
``o = (di+1)*9 + (dj+1)*3 + (dk+1)`` (:data:`OFFSETS`); ``o = CENTRE = 13`` is the voxel itself
and ``26 - o`` is the opposite offset of ``o``. The optional *far* offsets are +-2 along each
axis, numbered ``a = 2 * axis + (0: -2, 1: +2)`` (``FAR`` of them).
"""

import numpy as np

BLOCK = 8  # voxels per block edge
BLOCK_VOXELS = BLOCK ** 3
MAP_BLOCKS = 1024  # blocks per axis of the TSDF's block map (kernels.tsdf), centred on the
#                    grid's origin: blocks [-MAP_BLOCKS / 2, MAP_BLOCKS / 2), i.e. 8192 voxels
KEY_BITS = 21  # bits per axis of a block key
KEY_BIAS = 1 << (KEY_BITS - 1)  # block coordinates in [-2^20, 2^20) (8.4M voxels per axis)
KEY_MASK = (1 << KEY_BITS) - 1

STENCIL = 27  # offsets {-1, 0, 1}^3
CENTRE = 13  # offset of the voxel itself: (0, 0, 0)

FAR = 6  # far offsets +-2 along each axis (a = 2 * axis + (0: -2, 1: +2))


def stencil_offset(o: int) -> tuple[int, int, int]:
    """Voxel offset (di, dj, dk) in {-1, 0, 1}^3 of stencil offset
    o = (di+1) 9 + (dj+1) 3 + (dk+1)."""
    return o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1


OFFSETS = np.array([stencil_offset(o) for o in range(STENCIL)], np.int32)
"""(27, 3) int32: stencil offset o -> (di, dj, dk); o = CENTRE is the voxel itself."""


def stencil_offsets(kind: int) -> tuple[list[int], list[float]]:
    """Offsets of the 6-, 18- or 26-neighbour stencil and their membrane weights.

    Returns ``(offsets, weights)``: the offset indices o (0..26, without the centre 13) with
    ``|offset|^2 <= 1, 2, 3`` for ``kind = 6, 18, 26``, in ascending order, and the weights
    ``1 / |offset|^2`` (offset in voxels: 1 for a face, 1/2 for an edge, 1/3 for a corner
    neighbour). ``OPPOSITE(o) = 26 - o`` is in the list whenever ``o`` is, with the same weight.
    """
    if kind not in (6, 18, 26):
        raise ValueError(f"stencil must be 6, 18 or 26 neighbours, got {kind!r}")
    max_sq = {6: 1, 18: 2, 26: 3}[kind]
    sq = (OFFSETS.astype(np.int64) ** 2).sum(axis=1)
    offsets = [o for o in range(STENCIL) if 0 < sq[o] <= max_sq]
    return offsets, [1.0 / float(sq[o]) for o in offsets]


def block_key_np(blocks: np.ndarray) -> np.ndarray:
    """int64 key of integer block coordinates (..., 3); ascending keys = lexicographic blocks.
    The one definition of the packing (module docstring)."""
    b = np.asarray(blocks, dtype=np.int64) + KEY_BIAS
    return (b[..., 0] << 42) | (b[..., 1] << 21) | b[..., 2]


def decode_keys(keys: np.ndarray) -> np.ndarray:
    """Block coordinates (B, 3) int64 of block keys (B,) (inverse of :func:`block_key_np`)."""
    k = np.asarray(keys, np.int64)
    return np.stack([(k >> (2 * KEY_BITS)) & KEY_MASK, (k >> KEY_BITS) & KEY_MASK, k & KEY_MASK],
                    axis=1) - KEY_BIAS


def block_key_steps() -> np.ndarray:
    """(27,) int64: ``block_key(b + offset_o) - block_key(b)`` for the stencil offsets (keys are
    linear in the coordinates while every coordinate stays inside the key range)."""
    return block_key_np(OFFSETS) - block_key_np(np.zeros(3, np.int64))


def column_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=0)`` of a 2-d array, one column at a time: numpy reduces an (N, 3) array
    along axis 0 7-14x slower than each of its columns (45 against 3-7 ms on 3.4M voxels'
    ijk); the same values."""
    return np.array([a[:, k].min() for k in range(a.shape[1])], dtype=a.dtype)


def column_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=0)`` of a 2-d array, one column at a time (:func:`column_min`)."""
    return np.array([a[:, k].max() for k in range(a.shape[1])], dtype=a.dtype)


def band_box(block_keys: np.ndarray) -> np.ndarray:
    """(lo, hi) float64 (6,): the voxel box ``[8 b_min, 8 (b_max + 1)]`` of the blocks in
    ``block_keys`` (per axis). Cells of the trilinear lattice based outside it have no corner in
    those blocks."""
    if len(block_keys) == 0:
        return np.zeros(6)
    blocks = decode_keys(block_keys)
    return np.concatenate([blocks.min(axis=0) * BLOCK, (blocks.max(axis=0) + 1) * BLOCK]).astype(
        np.float64)


#: Largest bounding box (in blocks) :func:`distinct_block_keys` marks in a bitmap (16 MB).
DISTINCT_BITMAP = 1 << 24


def distinct_block_keys(blocks: np.ndarray) -> np.ndarray:
    """``np.unique(block_key_np(blocks))``: the distinct keys of integer block coordinates (M,
    3) (float arrays of whole numbers too), ascending. The blocks are marked in a bitmap over
    their bounding box, whose flat order is the keys' (lexicographic), when it holds at most
    :data:`DISTINCT_BITMAP` blocks, which spares the sort of M keys; sorted otherwise."""
    b = np.asarray(blocks).reshape(-1, 3).astype(np.int64)
    if not len(b):
        return np.zeros(0, np.int64)
    lo, hi = column_min(b), column_max(b)
    dims = [int(n) for n in hi - lo + 1]
    if dims[0] * dims[1] * dims[2] > DISTINCT_BITMAP:
        return np.unique(block_key_np(b))
    seen = np.zeros(dims[0] * dims[1] * dims[2], bool)
    seen[((b[:, 0] - lo[0]) * dims[1] + (b[:, 1] - lo[1])) * dims[2] + (b[:, 2] - lo[2])] = True
    i, rest = np.divmod(np.flatnonzero(seen), dims[1] * dims[2])
    j, k = np.divmod(rest, dims[2])
    return block_key_np(np.stack([i + lo[0], j + lo[1], k + lo[2]], axis=1))
