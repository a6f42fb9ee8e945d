"""Per-voxel ``@ti.func`` helpers shared by the kernels of several modules (written once).

* :func:`floor_i32` -- floor without a libm call;
* :func:`offset_of` -- the Taichi side of :func:`kernels.layout.stencil_offset`, for a
  run-time stencil offset;
* :func:`block_key`, :func:`find_block`, :func:`block_row` -- the Taichi side of the block keys
  of :mod:`kernels.layout` and the binary search over sorted keys (the band lookup of
  :mod:`kernels.lookup`);
* :func:`reaches_block`, :func:`cell_corners` -- the blocks a trilinear cell reaches, and the
  band indices of its 8 corners;
* :func:`corner`, :func:`trilinear` -- the cell corners ``c = 4 ci + 2 cj + ck`` and their
  trilinear weights;
* :func:`block_mean_depth`, :func:`block_is_planar` -- the mean depth of a k x k block of pixels
  on one surface, and whether the block is one plane within the sensor noise.

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
def offset_of(o):
    """Voxel offset (di, dj, dk) of stencil offset ``o``, a run-time value, as an int32
    vector: :func:`kernels.layout.stencil_offset` in Taichi (a Python function called in a
    kernel would run at compile time, which Taichi warns of on every process's first call)."""
    return ti.Vector([o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1], ti.i32)


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
def corner_offset(s: ti.i32):
    """Offset (3,) int32 of cell corner (or neighbour block) s = 4 ci + 2 cj + ck at run time
    (:func:`corner` at compile time)."""
    return ti.Vector([(s >> 2) & 1, (s >> 1) & 1, s & 1])


@ti.func
def reaches_block(c0, b, s: ti.i32) -> ti.i32:
    """1 if the cell with base corner c0 has a corner in block ``b + corner_offset(s)`` (b = c0
    // 8): a cell leaves its block along an axis only from the block's last voxel layer, so
    most cells reach block b alone and need one block lookup, not eight."""
    last = (c0 - b * BLOCK) == BLOCK - 1
    return ti.cast(((corner_offset(s) == 0) | last).all(), ti.i32)


@ti.func
def cell_corners(block_table: ti.template(), c0, b, rows):
    """Band indices (8,) int32 of the corners ``c0 + corner(c)`` of the cell with base corner
    c0, given its block ``b = c0 // 8`` and the table rows (8,) of blocks ``b + corner(s)``
    (-1: not in the band; at least those the cell reaches). Stops at the first corner
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


#: A k x k block is one planar surface when its pixels' RMS deviation from their least-squares
#: plane is at most PLANE_NOISE times the axial depth noise at its mean depth
#: (:func:`block_is_planar`): pure noise passes (its RMS is about the noise), a step, a crease
#: or a curve that bends by more than the noise within the block does not.
PLANE_NOISE = 2.0


@ti.func
def block_is_planar(depth: ti.template(), by: ti.i32, bx: ti.i32, k: ti.template(),
                    mean: ti.f32, noise_a: ti.f64, noise_b: ti.f64, noise_z0: ti.f64) -> ti.i32:
    """1 if the k x k block ``[by k, by k + k) x [bx k, bx k + k)`` of ``depth``, whose mean
    depth is ``mean`` (:func:`block_mean_depth`), is one plane within the sensor noise: the
    RMS of the depths' residuals from their least-squares plane, ``d ~ c + g_u du + g_v dv``,
    is at most ``PLANE_NOISE (noise_a + noise_b (mean - noise_z0)^2)``, the axial noise at the
    mean depth (metres). On a plane the block's mean is the surface at its centre; where the
    block straddles a step or a crease, or a curve bends within it, the mean lies on no
    surface. The plane is fitted over the block's own pixels for k >= 4, and over the 4 x 4
    pixels of a 2 x 2 block and its ring for k = 2: four pixels leave the plane one degree of
    freedom, and a step between a block's two columns is a plane (a ring pixel without depth
    or outside the image refuses the block: it borders an edge).

    The plane's residual sum of squares over an ``r x r`` window is ``sum e^2 - (sum e)^2 / r^2
    - (S_u^2 + S_v^2) / S_uu`` (the pixel offsets from the window's centre are orthogonal to
    each other and to the constant on the square grid), ``e`` the depths less the block's mean
    (float64, so the sum does not cancel), ``S_u = sum e (du - (r - 1) / 2)``, ``S_uu = r^2 (r^2
    - 1) / 12``."""
    g = ti.static(1 if k == 2 else 0)  # the ring of a 2 x 2 block
    r = ti.static(k + 2 * g)
    d_ref = ti.cast(mean, ti.f64)
    s1, s2, su, sv = ti.f64(0.0), ti.f64(0.0), ti.f64(0.0), ti.f64(0.0)
    ok = 1
    for dv in range(r):
        for du in range(r):
            vv, uu = by * k + dv - g, bx * k + du - g
            d = ti.f32(0.0)
            if 0 <= vv < depth.shape[0] and 0 <= uu < depth.shape[1]:
                d = depth[vv, uu]
            if d <= 0:
                ok = 0  # a ring pixel without depth: an edge
            e = ti.cast(d, ti.f64) - d_ref
            s1 += e
            s2 += e * e
            su += e * (ti.cast(du, ti.f64) - ti.static((r - 1) / 2.0))
            sv += e * (ti.cast(dv, ti.f64) - ti.static((r - 1) / 2.0))
    n = ti.static(float(r * r))
    rss = s2 - s1 * s1 / n - (su * su + sv * sv) / ti.static(r * r * (r * r - 1) / 12.0)
    sd = noise_a + noise_b * (d_ref - noise_z0) ** 2
    if rss > n * (PLANE_NOISE * sd) ** 2:
        ok = 0
    return ok
