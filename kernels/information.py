"""The information a depth frame gives each band voxel, ``(A^T W A)_ii``, alone: what
next-best-view planning needs of a hypothetical frame (:meth:`kernels.observe.Observer.information`).

The same per-row code as the data term (:func:`kernels.dataterm.observe_row`, mode
``MODE_DIAGONAL``): the same samples, rows, gate and weights, and the same fixed-point
rounding of each contribution ``w a_c a_c``, so the diagonal equals bit for bit that of the
full accumulators (:meth:`~kernels.observe.Observer.diagonal` after ``integrate``), at 8 adds
a sample instead of 44 and 8 bytes a voxel per thread instead of 128.
"""

import taichi as ti

from .dataterm import MODE_DIAGONAL, observe_part
from .stencil import first_chunk, virtual_iterations

_NDA = ti.types.ndarray


@ti.kernel
def information_frame(depth: _NDA(dtype=ti.f32, ndim=2), mask: _NDA(dtype=ti.i8, ndim=2),
                      prm: _NDA(dtype=ti.f64, ndim=1), block_hash: _NDA(dtype=ti.i64, ndim=1),
                      block_table: _NDA(dtype=ti.i32, ndim=2), ref: _NDA(dtype=ti.f32, ndim=1),
                      stride: ti.i32, m: ti.i32, mf: ti.i32, n_parts: ti.i32,
                      D_acc: _NDA(dtype=ti.i64, ndim=1),
                      counts: _NDA(dtype=ti.i64, ndim=2), scratch: _NDA(dtype=ti.i32, ndim=1),
                      blocks: _NDA(dtype=ti.i32, ndim=1)):
    """One frame's ``w a_c^2`` into ``D_acc`` ((parts, N) int64, flattened as in
    :func:`kernels.dataterm.observe_frame`), each thread into its own part
    (rows dealt out as in :func:`kernels.dataterm.observe_frame`). Integer adds without
    atomics: deterministic."""
    n_vox = D_acc.shape[0] // n_parts
    n_virtual = ti.max(n_parts, ti.static(virtual_iterations()))
    for t in range(n_virtual):
        for part in range(first_chunk(t, n_parts, n_virtual),
                          first_chunk(t + 1, n_parts, n_virtual)):
            observe_part(part, n_parts, n_vox, depth, mask, prm, block_hash, block_table, ref,
                         stride, m, mf, counts, scratch, blocks, (D_acc,), MODE_DIAGONAL)
