"""The fused SDF as Taichi fields with ``@ti.func`` accessors, for other people's Taichi code.

:class:`SDFField` holds one narrow band (DESIGN.md 3, step 2: the band voxels ``ijk``, their
posterior mean and variance, and which voxels were observed) in Taichi *fields* and offers
``@ti.func`` methods that a kernel written anywhere can call::

    import taichi as ti
    import kernels

    ti.init(arch=ti.cpu)                        # the embedding program's own init
    field = kernels.SDFField.from_posterior(post)   # or SDFField(ijk, mean, var, observed, vs)

    @ti.kernel
    def step(sdf: ti.template()):               # pass it as a template: see rule 4 below
        for i in x:
            if sdf.is_observed(x[i]):
                d = sdf.sdf(x[i])               # metres, positive in free space
                n = sdf.grad(x[i])              # unit normal, world frame
    step(field)

Geometry (DESIGN.md 2): world frame, metres. Voxel ``ijk`` has its centre at
``(ijk + 0.5) voxel_size``. A point ``p`` is interpolated trilinearly over the cell of voxel
centres around it, exactly step 3 of kernels/observe.py: grid coordinate
``g = p / voxel_size - 0.5``, base corner ``c0 = floor(g)``, fraction ``f = g - c0``, corner
``c0 + (ci, cj, ck)`` with weight ``prod(f if c else 1 - f)``. ``p`` is *observed* when all 8
corners are band voxels with ``observed`` set; every value below is defined only there.

Accessors (``p``: a 3-vector, f32 or f64, world metres; all return f32; pure reads, so
deterministic and safe in any parallel loop; one cell lookup each):

* ``is_observed(p)`` -> i32: 1 where defined, else 0.
* ``sdf(p)`` -> the trilinear posterior mean, metres; :data:`UNOBSERVED` (1e6 m, "far, free")
  where not observed, so a contact test ``sdf(p) < r`` is false there.
* ``grad(p)`` -> unit 3-vector, the normalised *analytic* gradient of the trilinear mean
  (the derivative of the interpolant itself, not central differences: continuous inside a
  cell, it jumps across cell faces as the interpolant's slope does). Zero vector where not
  observed or where the gradient vanishes.
* ``sigma(p)`` -> ``sqrt(max(trilinear var, 0))``, the posterior standard deviation of the
  SDF, metres; :data:`UNOBSERVED` where not observed (unknown = unbounded uncertainty).
* ``query(p)`` -> ``(sdf, grad, sigma, observed)``: all four from one lookup (what a
  simulation step wants; ``is_observed`` and friends are this function's parts).

Lookup cost: a box test against the band's blocks (points outside cost a few compares), then
a binary search over the B sorted block keys (log2 B steps) for the cell's block, plus one more
per neighbour block the cell reaches on the block's last voxel layer (kernels/lookup.py).

Rules an embedder must know (verified on Taichi 1.7.4, CPU):

1. **ti.init**: the embedding program calls ``ti.init`` (or ``bftaichi.init``) before creating
   an SDFField. ``kernels`` never calls it, neither at import nor later; the constructor
   raises RuntimeError when Taichi is not initialised.
2. **Field placement**: the constructor places all fields, in one SNode tree of its own
   (``ti.FieldsBuilder``): ``block_keys`` (B,) i64, ``block_table`` (B, 512) i32,
   ``mean`` / ``var`` (N,) f32, ``observed`` (N,) u8. Creating it before or after the
   program's first kernel launch both work (Taichi >= 1.0 finalises each new tree on its own;
   tested: fields made after kernels ran, and kernels compiled before, keep working).
   :meth:`SDFField.destroy` frees the tree (the object must not be used afterwards).
3. **Copies**: the fields hold a *copy* of the arrays. A new solve on the same band (same
   ``ijk``) is taken over with :meth:`SDFField.update`; a new band (other voxels) needs a new
   SDFField (and, if the old one is no longer wanted, ``old.destroy()``). ``ti.reset`` or a
   second ``ti.init`` invalidate every field: build the SDFField again after them.
4. **Kernels and objects**: Taichi compiles a kernel against the SDFField it sees at its first
   call. A kernel that reads a *global* SDFField keeps reading that object even after the
   Python name is rebound; pass the field as a ``ti.template()`` argument when it can change.
   Each distinct object costs one compilation of the user's kernel (about 0.1-3 s on first
   use; Taichi's offline cache serves later runs). ``update`` keeps the object: no recompile.

Cost (examples/particles_collide.py via tools/bench_embed.py; 2 threads of a shared 2-core
Xeon): 10k particles resting on a 16k-voxel, 80-block tabletop band at 3 cm take 0.7-1.2 ms per
step with ``query``, 2.2-2.5x the exact analytic SDF of the same five primitives (central-
difference normal, 7 evaluations).
"""

import numpy as np
import taichi as ti
from taichi.lang import impl

from .funcs import (block_row, cell_corners, corner, corner_offset, floor_i32,
                    reaches_block, trilinear)
from .layout import BLOCK, BLOCK_VOXELS, KEY_BIAS, band_box
from .lookup import build_block_table

UNOBSERVED = 1.0e6
"""sdf and sigma where a point is not observed, metres (far: no contact; unbounded sigma)."""


@ti.func
def _cell_rows(block_keys: ti.template(), c0, b):
    """Table rows (8,) of the blocks ``b + corner(s)`` that the cell with base corner c0 (in
    block b) reaches (:func:`kernels.funcs.reaches_block`), -1 for those it does not reach or
    that hold no band voxel."""
    rows = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
    for s in range(8):
        if reaches_block(c0, b, s):
            nb = b + corner_offset(s)
            rows[s] = block_row(block_keys, nb[0], nb[1], nb[2])
    return rows


@ti.func
def _trilinear_grad(f):
    """d a_c / d f (3, 8) float64: the derivatives of the 8 weights of :func:`trilinear`
    along each axis, corner c = 4 ci + 2 cj + ck."""
    w = ti.Matrix([[1.0 - f[0], f[0]], [1.0 - f[1], f[1]], [1.0 - f[2], f[2]]], dt=ti.f64)
    s = ti.Vector([-1.0, 1.0], dt=ti.f64)  # d(1 - f)/df, df/df
    return ti.Matrix([[s[ti.static(corner(c)[0])] * w[1, ti.static(corner(c)[1])]
                       * w[2, ti.static(corner(c)[2])] for c in ti.static(range(8))],
                      [w[0, ti.static(corner(c)[0])] * s[ti.static(corner(c)[1])]
                       * w[2, ti.static(corner(c)[2])] for c in ti.static(range(8))],
                      [w[0, ti.static(corner(c)[0])] * w[1, ti.static(corner(c)[1])]
                       * s[ti.static(corner(c)[2])] for c in ti.static(range(8))]], dt=ti.f64)


def _as_1d(name: str, a, n: int, kind: str) -> np.ndarray:
    a = np.asarray(a)
    if a.shape != (n,):
        raise ValueError(f"SDFField: {name} must have shape ({n},) like ijk, got {a.shape}")
    if kind == "float":
        if not np.issubdtype(a.dtype, np.floating):
            raise TypeError(f"SDFField: {name} must be a float array, got {a.dtype}")
        if not np.isfinite(a).all():
            raise ValueError(f"SDFField: {name} contains NaN or inf")
    elif a.dtype != np.bool_:
        raise TypeError(f"SDFField: {name} must be a bool array, got {a.dtype}")
    return a


@ti.data_oriented
class SDFField:
    """A fused narrow band in Taichi fields, with ``@ti.func`` accessors (module docstring).

    Args:
        ijk: (N, 3) integer voxel indices of the band, unique, N >= 1 (centre
            ``(ijk + 0.5) voxel_size``; block coordinates ``ijk // 8`` within +-2^20).
        mean: (N,) float posterior mean SDF, metres, positive in free space.
        var: (N,) float posterior variance of the SDF, metres^2, >= 0.
        observed: (N,) bool, voxel observed (a posterior's ``weight > 0``).
        voxel_size: voxel edge, metres, > 0.

    Attributes: ``voxel_size`` (float, metres), ``n_voxels`` N, ``n_blocks`` B and the fields
    ``block_keys``, ``block_table``, ``mean``, ``var``, ``observed`` (module docstring, rule 2).
    Raises ValueError/TypeError naming the argument, RuntimeError if Taichi is not initialised.
    """

    def __init__(self, ijk, mean, var, observed, voxel_size: float):
        if impl.get_runtime().prog is None:
            raise RuntimeError("SDFField: Taichi is not initialised: call ti.init (or "
                               "bftaichi.init) before creating an SDFField")
        ijk = np.asarray(ijk)
        if ijk.ndim != 2 or ijk.shape[1] != 3 or len(ijk) == 0:
            raise ValueError(f"SDFField: ijk must be a non-empty (N, 3) array, got {ijk.shape}")
        if not np.issubdtype(ijk.dtype, np.integer):
            raise TypeError(f"SDFField: ijk must be an integer array, got {ijk.dtype}")
        blocks = np.floor_divide(ijk.astype(np.int64), BLOCK)
        if blocks.min() < -KEY_BIAS or blocks.max() >= KEY_BIAS:
            raise ValueError(f"SDFField: ijk reaches beyond +-{KEY_BIAS * BLOCK} voxels")
        if len(np.unique(ijk, axis=0)) != len(ijk):
            raise ValueError("SDFField: ijk holds duplicate voxels")
        voxel_size = float(voxel_size)
        if not (np.isfinite(voxel_size) and voxel_size > 0):
            raise ValueError(f"SDFField: voxel_size = {voxel_size} must be a positive number")
        n = len(ijk)
        keys, table = build_block_table(ijk)
        self.voxel_size = voxel_size
        self.n_voxels = n
        self.n_blocks = len(keys)
        # Valid base corners c0 lie in a band block: g in [8 b_min, 8 (b_max + 1)) per axis
        # (Python constants, compiled into the accessors).
        box = band_box(keys)
        self._g_lo = tuple(float(x) for x in box[:3])
        self._g_hi = tuple(float(x) for x in box[3:])
        # One SNode tree holds the whole band (module docstring, rule 2).
        fb = ti.FieldsBuilder()
        self.block_keys = ti.field(ti.i64)
        self.block_table = ti.field(ti.i32)
        self.mean = ti.field(ti.f32)
        self.var = ti.field(ti.f32)
        self.observed = ti.field(ti.u8)
        fb.dense(ti.i, self.n_blocks).place(self.block_keys)
        fb.dense(ti.ij, (self.n_blocks, BLOCK_VOXELS)).place(self.block_table)
        fb.dense(ti.i, n).place(self.mean, self.var, self.observed)
        self._tree = fb.finalize()
        self._prog = impl.get_runtime().prog
        self.block_keys.from_numpy(keys)
        self.block_table.from_numpy(table)
        self.update(mean, var, observed)

    @classmethod
    def from_posterior(cls, post) -> "SDFField":
        """From any object with ``ijk``, ``mean``, ``var``, ``weight`` and ``voxel_size``
        (e.g. ``bftaichi.posterior.Posterior``); observed = ``weight > 0``."""
        return cls(post.ijk, post.mean, post.var, np.asarray(post.weight) > 0, post.voxel_size)

    def update(self, mean, var, observed) -> None:
        """Copy new values for the same band (same ``ijk``, same order): ``mean`` (N,) metres,
        ``var`` (N,) metres^2 >= 0, ``observed`` (N,) bool. Kernels compiled against this
        object stay valid. A different band needs a new SDFField."""
        if self._tree is None or impl.get_runtime().prog is not self._prog:
            raise RuntimeError("SDFField: the fields are gone (destroy(), ti.reset or a new "
                               "ti.init): build a new SDFField")
        n = self.n_voxels
        mean = _as_1d("mean", mean, n, "float")
        var = _as_1d("var", var, n, "float")
        observed = _as_1d("observed", observed, n, "bool")
        if var.min() < 0:
            raise ValueError(f"SDFField: var has negative entries (min {var.min()})")
        self.mean.from_numpy(mean.astype(np.float32))
        self.var.from_numpy(var.astype(np.float32))
        self.observed.from_numpy(observed.astype(np.uint8))

    def destroy(self) -> None:
        """Free the fields' memory; the object (and kernels compiled against it) must not be
        used afterwards."""
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None

    # -- accessors (module docstring) ----------------------------------------------------------

    @ti.func
    def _cell(self, p):
        """``(idx, f, valid)`` of world point p: band indices (8,) of its cell's corners,
        fraction f (3,) float64 and 1 if all 8 corners are observed band voxels."""
        g = ti.cast(p, ti.f64) * (1.0 / self.voxel_size) - 0.5
        lo = ti.Vector(self._g_lo, dt=ti.f64)
        hi = ti.Vector(self._g_hi, dt=ti.f64)
        idx = ti.Vector([-1, -1, -1, -1, -1, -1, -1, -1])
        f = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        valid = 0
        if ((g >= lo) & (g < hi)).all():  # also false for NaN; keeps the i32 floor in range
            c0 = floor_i32(g)
            f = g - ti.cast(c0, ti.f64)
            b = c0 // BLOCK  # floors (c0 >= 8 b_min may be negative)
            idx = cell_corners(self.block_table, c0, b, _cell_rows(self.block_keys, c0, b))
            if idx[7] >= 0:
                valid = 1
                for c in range(8):
                    if self.observed[idx[c]] == 0:
                        valid = 0
        return idx, f, valid

    @ti.func
    def query(self, p):
        """``(sdf, grad, sigma, observed)`` at world point p: f32 metres, f32 unit 3-vector,
        f32 metres, i32 1/0 (module docstring; one lookup). Deterministic (pure reads)."""
        idx, f, valid = self._cell(p)
        d = ti.cast(UNOBSERVED, ti.f64)
        s = ti.cast(UNOBSERVED, ti.f64)
        n = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        if valid:
            a = trilinear(f)
            da = _trilinear_grad(f)
            d = 0.0
            s = 0.0
            for c in ti.static(range(8)):
                m = ti.cast(self.mean[idx[c]], ti.f64)
                d += a[c] * m
                s += a[c] * ti.cast(self.var[idx[c]], ti.f64)
                n += ti.Vector([da[0, c], da[1, c], da[2, c]]) * m
            s = ti.sqrt(ti.max(s, 0.0))
            norm = n.norm()  # the 1 / voxel_size of dg/dp cancels in the normalisation
            if norm > 0:
                n /= norm
        return ti.cast(d, ti.f32), ti.cast(n, ti.f32), ti.cast(s, ti.f32), valid

    @ti.func
    def is_observed(self, p) -> ti.i32:
        """1 if all 8 corners of p's cell are observed band voxels, else 0."""
        idx, f, valid = self._cell(p)
        return valid

    @ti.func
    def sdf(self, p) -> ti.f32:
        """Trilinear posterior mean at world point p, metres; UNOBSERVED where not observed."""
        d, n, s, valid = self.query(p)
        return d

    @ti.func
    def grad(self, p):
        """Unit normal (f32 3-vector, world frame) at p: the normalised analytic gradient of
        the trilinear mean; zero where not observed or where the gradient vanishes."""
        d, n, s, valid = self.query(p)
        return n

    @ti.func
    def sigma(self, p) -> ti.f32:
        """Posterior standard deviation of the SDF at p, ``sqrt(trilinear var)``, metres;
        UNOBSERVED where not observed."""
        d, n, s, valid = self.query(p)
        return s


@ti.kernel
def query_points(field: ti.template(), p: ti.types.ndarray(dtype=ti.f64, ndim=2),
                 sdf: ti.types.ndarray(dtype=ti.f32, ndim=1),
                 grad: ti.types.ndarray(dtype=ti.f32, ndim=2),
                 sigma: ti.types.ndarray(dtype=ti.f32, ndim=1),
                 observed: ti.types.ndarray(dtype=ti.u8, ndim=1)):
    """:meth:`SDFField.query` at each row of ``p`` (M, 3) (the field's frame, metres), into
    ``sdf`` (M,), ``grad`` (M, 3), ``sigma`` (M,) and ``observed`` (M,): the numpy front door
    of ``bftaichi.Posterior.query``. One thread per point, pure reads (deterministic)."""
    for i in range(p.shape[0]):
        d, n, s, v = field.query(ti.Vector([p[i, 0], p[i, 1], p[i, 2]]))
        sdf[i] = d
        sigma[i] = s
        observed[i] = ti.cast(v, ti.u8)
        for a in ti.static(range(3)):
            grad[i, a] = n[a]
