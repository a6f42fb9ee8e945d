"""A principal submatrix of the band's stencil: Q restricted to a set of band voxels, in the
stencil contract of :mod:`kernels.stencil` (the MAP's local free-space passes solve on one).

One pass over the rows' neighbour tables, parallel over rows (each output row written by one
thread, no atomics): the same arrays as the numpy gathers ``loc[nbr[rows]]`` and
``where(nbr_r >= 0, S[rows], 0)``, without their (rows, 27) temporaries.
"""

import numpy as np
import taichi as ti

_NDA = ti.types.ndarray


@ti.kernel
def _restrict(rows: _NDA(dtype=ti.i64, ndim=1), loc: _NDA(dtype=ti.i32, ndim=1),
              S: _NDA(dtype=ti.f32, ndim=2), nbr: _NDA(dtype=ti.i32, ndim=2),
              S_r: _NDA(dtype=ti.f32, ndim=2), nbr_r: _NDA(dtype=ti.i32, ndim=2)):
    """Row ``q`` of the result is band row ``rows[q]``, its neighbours renumbered by ``loc``
    (-1 where the neighbour is missing or outside the rows, its coefficient then 0)."""
    for q in range(rows.shape[0]):
        i = rows[q]
        for o in range(nbr.shape[1]):
            j = nbr[i, o]
            k = -1
            if j >= 0:
                k = loc[j]
            nbr_r[q, o] = k
            S_r[q, o] = S[i, o] if k >= 0 else ti.f32(0.0)


def principal_submatrix(S: np.ndarray, nbr: np.ndarray, far, rows: np.ndarray,
                        loc: np.ndarray | None = None) -> tuple:
    """The stencil of Q's principal submatrix on the band voxels ``rows`` (sorted, unique):
    ``(S_r, nbr_r, far_r)`` with the rows' own numbering, links leaving ``rows`` cut. ``S``
    (N, 27) float32 and ``nbr`` (N, 27) int32 as :func:`kernels.stencil.stencil_arrays`
    gives them, ``far`` None or its ``(S2, nbr2)`` (N, 6). ``loc``: an (N + 1,) int32 scratch
    of -1, left so."""
    n = len(S)
    if loc is None:
        loc = np.full(n + 1, -1, np.int32)
    rows = np.ascontiguousarray(rows, np.int64)
    m = len(rows)
    loc[rows] = np.arange(m, dtype=np.int32)
    out = []
    for coef, links in [(S, nbr)] + ([] if far is None else [far]):
        coef = np.ascontiguousarray(coef, np.float32)  # no copy of the solver's own arrays
        links = np.ascontiguousarray(links, np.int32)
        coef_r = np.empty((m, coef.shape[1]), np.float32)
        links_r = np.empty((m, links.shape[1]), np.int32)
        if m:
            _restrict(rows, loc, coef, links, coef_r, links_r)
        out.append((coef_r, links_r))
    loc[rows] = -1
    return out[0][0], out[0][1], (out[1] if far is not None else None)
