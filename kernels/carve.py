"""Free space seen by the rays: per band voxel, how many frames observe it and how many of
those saw it farther than the bootstrap truncation in front of their measured surface.

The bootstrap TSDF (:mod:`kernels.tsdf`) averages every frame's clamped distance, so a voxel
that some rays passed through and that other frames place behind a thin surface (a slat, the
rim of a sheet) gets a small positive or negative average: neither free nor surface. The data
term (:mod:`kernels.observe`) samples only near each pixel's measured surface, so the rays
that passed through the voxel far in front of theirs say nothing there. Counted here, a voxel
that a good share of the frames saw as free space can be held out of the surface
(:func:`bftaichi.stages.solve.solve_map`).

Per frame and band voxel ``i`` (centre ``x = (ijk_i + 0.5) voxel``), as the bootstrap does:
``(u, v)`` the nearest pixel of ``K x_C``, ``sdf = D(u, v) - z_C``; the frame *observes* the
voxel if ``z_C > 0``, ``D > 0`` and ``sdf >= -tau_b``, and *carves* it if also ``sdf >= tau_b``
(the bootstrap's clamped value). Each voxel is counted by one thread per frame, in integers:
the counts are exact and independent of the frame order.

Cost: the voxels are taken in groups, their 8^3 blocks (:class:`FreeSpaceCounter` orders
them block by block), and a group whose box of voxel indices lies wholly behind the camera or
more than a pixel outside the image is skipped: the projection's ``z``, ``u z`` and ``v z``
are affine in the voxel index, so their extremes over the box are at its corners, and no
voxel of a skipped group passes the test above. On a 1 cm band of the redkitchen frames the
pass took ~5 ms a frame over every voxel, ~4 ms with the groups: a kitchen frame sees most
of the room (docs/measurements.md).
"""

import numpy as np
import taichi as ti

from .layout import block_key_np
from .stencil import first_chunk, virtual_iterations
from .tsdf import voxel_projection

_NDA = ti.types.ndarray

P_A = 0  # 9: A, row-major (kernels.tsdf.voxel_projection: K x_C of voxel ijk = A ijk + c)
P_C = 9  # 3: c
P_TRUNC = 12  # tau_b, metres
N_PARAMS = 13


@ti.func
def _project(prm: ti.template(), g):
    """``K x_C = (u z, v z, z)`` of voxel index ``g`` (float64 3-vector)."""
    return ti.Vector([prm[P_C + r] + prm[P_A + 3 * r] * g[0] + prm[P_A + 3 * r + 1] * g[1]
                      + prm[P_A + 3 * r + 2] * g[2] for r in ti.static(range(3))])


@ti.func
def _box_unseen(prm: ti.template(), lo, hi, W: ti.i32, H: ti.i32) -> ti.i32:
    """1 when no voxel of the index box ``[lo, hi]`` can pass the frame's test: the box is
    behind the camera (``z`` < -1 um at every corner), or in front of it and more than a
    pixel left, right, above or below the image (left: the pixel coordinate ``p_0 / z + 0.5
    < -1``, i.e. the affine ``p_0 + 1.5 z < 0``, at every corner; and so on); 0 otherwise."""
    z_lo, z_hi = ti.f64(1e300), ti.f64(-1e300)
    left, top = ti.f64(-1e300), ti.f64(-1e300)  # largest u z + 1.5 z, v z + 1.5 z
    right, bottom = ti.f64(1e300), ti.f64(1e300)  # smallest u z + 0.5 z - (W + 1) z, ...
    for c in ti.static(range(8)):
        g = ti.Vector([ti.cast(hi[a] if (c >> (2 - a)) & 1 else lo[a], ti.f64)
                       for a in ti.static(range(3))])
        p = _project(prm, g)
        z_lo, z_hi = ti.min(z_lo, p[2]), ti.max(z_hi, p[2])
        left, top = ti.max(left, p[0] + 1.5 * p[2]), ti.max(top, p[1] + 1.5 * p[2])
        right = ti.min(right, p[0] + (0.5 - W - 1.0) * p[2])
        bottom = ti.min(bottom, p[1] + (0.5 - H - 1.0) * p[2])
    unseen = ti.cast(z_hi < -1e-6, ti.i32)
    if z_lo > 1e-6 and (left < 0 or top < 0 or right > 0 or bottom > 0):
        unseen = 1
    return unseen


@ti.kernel
def carve_frame(ijk: _NDA(dtype=ti.i32, ndim=2), starts: _NDA(dtype=ti.i32, ndim=1),
                box: _NDA(dtype=ti.i32, ndim=2), depth: _NDA(dtype=ti.f32, ndim=2),
                prm: _NDA(dtype=ti.f64, ndim=1), counts: _NDA(dtype=ti.i32, ndim=2)):
    """``counts[i, 0] += carves``, ``counts[i, 1] += observes`` (module docstring) for one
    frame; the groups of voxels (rows ``starts[k]..starts[k + 1]``, index box ``box[k]`` = lo,
    hi) dealt out in contiguous chunks over the threads, a group outside the view skipped."""
    H, W = depth.shape[0], depth.shape[1]
    n = starts.shape[0] - 1
    n_virtual = ti.max(n, ti.static(virtual_iterations()))
    for t in range(n_virtual):
        for k in range(first_chunk(t, n, n_virtual), first_chunk(t + 1, n, n_virtual)):
            lo = ti.Vector([box[k, 0], box[k, 1], box[k, 2]])
            hi = ti.Vector([box[k, 3], box[k, 4], box[k, 5]])
            if not _box_unseen(prm, lo, hi, W, H):
                for i in range(starts[k], starts[k + 1]):
                    p = _project(prm, ti.Vector([ti.cast(ijk[i, 0], ti.f64),
                                                 ti.cast(ijk[i, 1], ti.f64),
                                                 ti.cast(ijk[i, 2], ti.f64)]))
                    z = p[2]
                    if z > 0:
                        uh, vh = p[0] / z + 0.5, p[1] / z + 0.5
                        if uh >= 0 and uh < W and vh >= 0 and vh < H:
                            d = ti.cast(depth[ti.cast(vh, ti.i32), ti.cast(uh, ti.i32)],
                                        ti.f64)
                            sdf = d - z
                            if d > 0 and sdf >= -prm[P_TRUNC]:
                                # one thread owns voxel i: plain adds, no atomics
                                counts[i, 1] = counts[i, 1] + 1
                                if sdf >= prm[P_TRUNC]:
                                    counts[i, 0] = counts[i, 0] + 1


def voxel_groups(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(starts (G + 1,) int32, box (G, 6) int32)``: the runs of consecutive rows of ``ijk``
    in one 8^3 block, and each run's index box (lo, hi)."""
    if not len(ijk):
        return np.zeros(1, np.int32), np.zeros((0, 6), np.int32)
    key = ijk >> 3
    starts = np.flatnonzero(np.any(key[1:] != key[:-1], axis=1)) + 1
    starts = np.concatenate([[0], starts, [len(ijk)]]).astype(np.int32)
    box = np.concatenate([np.minimum.reduceat(ijk, starts[:-1], axis=0),
                          np.maximum.reduceat(ijk, starts[:-1], axis=0)], axis=1)
    return starts, np.ascontiguousarray(box, np.int32)


class FreeSpaceCounter:
    """Carve counts of the band voxels ``ijk`` (N, 3) over the frames given to :meth:`add`.

    Args:
        ijk: (N, 3) int32 band voxel indices (local grid).
        voxel_size: metres.
        trunc_m: the bootstrap truncation ``tau_b``, metres.
    """

    def __init__(self, ijk: np.ndarray, voxel_size: float, trunc_m: float):
        ijk = np.ascontiguousarray(ijk, np.int32)
        # the voxels block by block (a band's rows are in ijk order: a block's voxels apart),
        # so that the kernel can skip a block out of view; counts kept in that order
        self._order = np.argsort(block_key_np(ijk >> 3), kind="stable")
        self.ijk = np.ascontiguousarray(ijk[self._order])
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.counts = np.zeros((len(self.ijk), 2), np.int32)
        self._prm = np.zeros(N_PARAMS, np.float64)
        self._starts, self._box = voxel_groups(self.ijk)

    def add(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray) -> None:
        """Count one frame: ``depth_m`` (H, W) float32 metres (0 invalid), ``K`` (3, 3),
        ``T_W_C`` (4, 4) camera-to-world in the band's local frame."""
        if not len(self.ijk):
            return
        prm = self._prm
        prm[P_A:P_A + 9], prm[P_C:P_C + 3] = voxel_projection(K, T_W_C, self.voxel_size)
        prm[P_TRUNC] = self.trunc_m
        carve_frame(self.ijk, self._starts, self._box, np.ascontiguousarray(depth_m, np.float32),
                    prm, self.counts)

    def _in_given_order(self, column: int) -> np.ndarray:
        out = np.empty(len(self.ijk), np.int32)
        out[self._order] = self.counts[:, column]
        return out

    def carved(self) -> np.ndarray:
        """(N,) int32 frames that saw each voxel as free beyond ``tau_b`` (the rows of the
        ``ijk`` given)."""
        return self._in_given_order(0)

    def observing(self) -> np.ndarray:
        """(N,) int32 frames that observed each voxel."""
        return self._in_given_order(1)
