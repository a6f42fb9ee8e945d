"""The band lookup (kernels/lookup.py) finds every band voxel and nothing else, negative indices too."""

import numpy as np
import taichi as ti

from kernels.lookup import band_index, build_block_hash, build_block_table, hashed_block_row


@ti.kernel
def _lookup_all(keys: ti.types.ndarray(dtype=ti.i64, ndim=1),
                table: ti.types.ndarray(dtype=ti.i32, ndim=2),
                query: ti.types.ndarray(dtype=ti.i32, ndim=2),
                out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    for n in range(query.shape[0]):
        out[n] = band_index(keys, table, query[n, 0], query[n, 1], query[n, 2])


def test_lookup_matches_a_dictionary():
    rng = np.random.default_rng(0)
    ijk = np.unique(rng.integers(-40, 40, size=(3000, 3)), axis=0).astype(np.int32)
    keys, table = build_block_table(ijk)
    query = np.concatenate([ijk, rng.integers(-50, 50, size=(3000, 3)).astype(np.int32)])
    out = np.empty(len(query), np.int32)
    _lookup_all(keys, table, query, out)
    index = {tuple(v): n for n, v in enumerate(ijk.tolist())}
    expected = np.array([index.get(tuple(q), -1) for q in query.tolist()], np.int32)
    np.testing.assert_array_equal(out, expected)
    assert (out[: len(ijk)] == np.arange(len(ijk))).all()


@ti.kernel
def _hashed_rows(block_hash: ti.types.ndarray(dtype=ti.i64, ndim=1),
                 query: ti.types.ndarray(dtype=ti.i32, ndim=2),
                 out: ti.types.ndarray(dtype=ti.i32, ndim=1)):
    for n in range(query.shape[0]):
        out[n] = hashed_block_row(block_hash, query[n, 0], query[n, 1], query[n, 2])


def test_the_hashed_block_lookup_finds_every_block_row_and_nothing_else():
    """kernels.lookup.build_block_hash / hashed_block_row (the observation kernels' lookup):
    the row of every block of the band, -1 for blocks around it, in sparse and in dense
    layouts (a dense one makes long probe runs), and the same table when built twice."""
    from kernels.layout import decode_keys

    rng = np.random.default_rng(3)
    for extent, n in ((400, 2000), (12, 3000), (3, 20)):
        ijk = np.unique(rng.integers(-extent * 8, extent * 8, size=(n, 3)), axis=0)
        keys, _ = build_block_table(ijk.astype(np.int32))
        table = build_block_hash(keys)
        np.testing.assert_array_equal(table, build_block_hash(keys))
        blocks = decode_keys(keys)
        around = np.unique((blocks[:, None, :] + rng.integers(-2, 3, (len(blocks), 4, 3)))
                           .reshape(-1, 3), axis=0)
        query = np.concatenate([blocks, around]).astype(np.int32)
        out = np.empty(len(query), np.int32)
        _hashed_rows(table, query, out)
        row = {tuple(b): r for r, b in enumerate(blocks.tolist())}
        np.testing.assert_array_equal(out, [row.get(tuple(q), -1) for q in query.tolist()])
