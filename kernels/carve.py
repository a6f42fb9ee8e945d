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
"""

import numpy as np
import taichi as ti

from .stencil import first_chunk, virtual_iterations
from .tsdf import voxel_projection

_NDA = ti.types.ndarray

P_A = 0  # 9: A, row-major (kernels.tsdf.voxel_projection: K x_C of voxel ijk = A ijk + c)
P_C = 9  # 3: c
P_TRUNC = 12  # tau_b, metres
N_PARAMS = 13


@ti.kernel
def carve_frame(ijk: _NDA(dtype=ti.i32, ndim=2), depth: _NDA(dtype=ti.f32, ndim=2),
                prm: _NDA(dtype=ti.f64, ndim=1), counts: _NDA(dtype=ti.i32, ndim=2)):
    """``counts[i, 0] += carves``, ``counts[i, 1] += observes`` (module docstring) for one
    frame; voxels dealt out in contiguous chunks over the threads."""
    H, W = depth.shape[0], depth.shape[1]
    n = ijk.shape[0]
    n_virtual = ti.max(n, ti.static(virtual_iterations()))
    for t in range(n_virtual):
        for i in range(first_chunk(t, n, n_virtual), first_chunk(t + 1, n, n_virtual)):
            g = ti.Vector([ti.cast(ijk[i, 0], ti.f64), ti.cast(ijk[i, 1], ti.f64),
                           ti.cast(ijk[i, 2], ti.f64)])
            p = ti.Vector([prm[P_C + r] + prm[P_A + 3 * r] * g[0] + prm[P_A + 3 * r + 1] * g[1]
                           + prm[P_A + 3 * r + 2] * g[2] for r in ti.static(range(3))])
            z = p[2]
            if z > 0:
                uh, vh = p[0] / z + 0.5, p[1] / z + 0.5
                if uh >= 0 and uh < W and vh >= 0 and vh < H:
                    d = ti.cast(depth[ti.cast(vh, ti.i32), ti.cast(uh, ti.i32)], ti.f64)
                    sdf = d - z
                    if d > 0 and sdf >= -prm[P_TRUNC]:
                        # one thread owns voxel i: plain adds, no atomics
                        counts[i, 1] = counts[i, 1] + 1
                        if sdf >= prm[P_TRUNC]:
                            counts[i, 0] = counts[i, 0] + 1


class FreeSpaceCounter:
    """Carve counts of the band voxels ``ijk`` (N, 3) over the frames given to :meth:`add`.

    Args:
        ijk: (N, 3) int32 band voxel indices (local grid).
        voxel_size: metres.
        trunc_m: the bootstrap truncation ``tau_b``, metres.
    """

    def __init__(self, ijk: np.ndarray, voxel_size: float, trunc_m: float):
        self.ijk = np.ascontiguousarray(ijk, np.int32)
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.counts = np.zeros((len(self.ijk), 2), np.int32)
        self._prm = np.zeros(N_PARAMS, np.float64)

    def add(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray) -> None:
        """Count one frame: ``depth_m`` (H, W) float32 metres (0 invalid), ``K`` (3, 3),
        ``T_W_C`` (4, 4) camera-to-world in the band's local frame."""
        if not len(self.ijk):
            return
        prm = self._prm
        prm[P_A:P_A + 9], prm[P_C:P_C + 3] = voxel_projection(K, T_W_C, self.voxel_size)
        prm[P_TRUNC] = self.trunc_m
        carve_frame(self.ijk, np.ascontiguousarray(depth_m, np.float32), prm, self.counts)

    def carved(self) -> np.ndarray:
        """(N,) int32 frames that saw each voxel as free beyond ``tau_b``."""
        return self.counts[:, 0].copy()

    def observing(self) -> np.ndarray:
        """(N,) int32 frames that observed each voxel."""
        return self.counts[:, 1].copy()
