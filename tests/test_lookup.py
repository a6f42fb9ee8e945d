"""The band lookup (kernels/lookup.py) finds every band voxel and nothing else, negative indices too."""

import numpy as np
import taichi as ti

from kernels.lookup import band_index, build_block_table


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
