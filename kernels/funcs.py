"""Per-voxel ``@ti.func`` helpers shared by the kernels of several modules (written once).

* :func:`floor_i32` -- floor without a libm call;
* :func:`block_key`, :func:`find_block`, :func:`block_row` -- the Taichi side of the block keys
  of :mod:`kernels.layout` and the binary search over sorted keys (the band lookup of
  :mod:`kernels.lookup`);
* :func:`block_rows`, :func:`cell_corners` -- band indices of the 8 corners of a trilinear cell;
* :func:`corner`, :func:`trilinear` -- the cell corners ``c = 4 ci + 2 cj + ck`` and their
  trilinear weights;
* :func:`block_mean_depth` -- the mean depth of a k x k block of pixels on one surface.

All of them are pure reads: deterministic in any kernel.
"""

import taichi as ti

from .layout import BLOCK, KEY_BIAS, KEY_BITS


@ti.func
def floor_i32(x):
    """floor(x) as int32 for |x| < 2^31 without a libm call (Taichi's CPU target has no
    SSE4.1 ``roundss``, so ti.floor is a function call): truncate, then step down where the
    truncation went up (negative non-integers)."""
    t = ti.cast(x, ti.i32)
    return t - ti.cast(t > x, ti.i32)  # the comparison promotes t to x's float type


@ti.func
def block_key(bi: ti.i64, bj: ti.i64, bk: ti.i64) -> ti.i64:
    """int64 key of block (bi, bj, bk): :func:`kernels.layout.block_key_np` in Taichi."""
    return (((bi + KEY_BIAS) << ti.static(2 * KEY_BITS)) | ((bj + KEY_BIAS) << ti.static(KEY_BITS))
            | (bk + KEY_BIAS))


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
def block_row(block_keys: ti.template(), bi: ti.i32, bj: ti.i32, bk: ti.i32) -> ti.i32:
    """Row of block (bi, bj, bk) in the block table, or -1."""
    return find_block(block_keys, block_key(ti.cast(bi, ti.i64), ti.cast(bj, ti.i64),
                                            ti.cast(bk, ti.i64)))


def corner(c: int) -> tuple[int, int, int]:
    """Offset (ci, cj, ck) in {0, 1}^3 of cell corner c = 4 ci + 2 cj + ck (compile time)."""
    return (c >> 2) & 1, (c >> 1) & 1, c & 1


@ti.func
def block_rows(block_keys: ti.template(), b):
    """Table rows (8,) int32 of blocks ``b + corner(s)``, s = 0..7 (-1: not in the band): every
    block a cell with its base corner in block b can reach."""
    rows = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
    for s in range(8):
        rows[s] = block_row(block_keys, b[0] + ((s >> 2) & 1), b[1] + ((s >> 1) & 1),
                            b[2] + (s & 1))
    return rows


@ti.func
def cell_corners(block_table: ti.template(), c0, b, rows):
    """Band indices (8,) int32 of the corners ``c0 + corner(c)`` of the cell with base corner
    c0, given its block ``b = c0 // 8`` and :func:`block_rows` of b. Stops at the first corner
    outside the band (it and the later ones are -1). Table reads only; the run-time corner loop
    keeps the compiled code (and Taichi's compile time) small."""
    loc = c0 - b * BLOCK
    idx = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
    for c in range(8):
        lc = loc + ti.Vector([(c >> 2) & 1, (c >> 1) & 1, c & 1])
        up = ti.cast(lc >= BLOCK, ti.i32)  # corner in the next block along that axis
        row = rows[up[0] * 4 + up[1] * 2 + up[2]]
        lc -= up * BLOCK
        found = -1
        if row >= 0:
            found = block_table[row, lc[0] * 64 + lc[1] * 8 + lc[2]]
        idx[c] = found
        if found < 0:
            break
    return idx


@ti.func
def trilinear(f):
    """The 8 trilinear weights (float64) of fraction f in [0, 1)^3, corner c = 4 ci + 2 cj + ck."""
    w = ti.Matrix([[1.0 - f[0], f[0]], [1.0 - f[1], f[1]], [1.0 - f[2], f[2]]], dt=ti.f64)
    return ti.Vector([w[0, ti.static(corner(c)[0])] * w[1, ti.static(corner(c)[1])]
                      * w[2, ti.static(corner(c)[2])] for c in ti.static(range(8))], dt=ti.f64)


@ti.func
def block_mean_depth(depth: ti.template(), by: ti.i32, bx: ti.i32, k: ti.template(),
                     reach: ti.f32) -> ti.f32:
    """Mean depth of pixels ``[by k, by k + k) x [bx k, bx k + k)`` of ``depth`` if all are
    valid (> 0) and lie on one surface (they differ by at most ``k reach mean``; ``reach =
    tan(max slope) / fx``, a surface inclined by at most that slope), else 0."""
    lo, hi, total = ti.f32(1e30), ti.f32(0.0), ti.f32(0.0)
    for dv in range(k):
        for du in range(k):
            d = depth[by * k + dv, bx * k + du]
            lo, hi, total = ti.min(lo, d), ti.max(hi, d), total + d
    mean = total / ti.static(float(k * k))
    out = ti.f32(0.0)
    if lo > 0 and hi - lo <= reach * ti.static(float(k)) * mean:
        out = mean
    return out
