"""Sparse projective TSDF (Curless & Levoy), the bootstrap of BayesFusion-SDF (DESIGN.md 3.1).

Field layout (all declared in :meth:`SparseTSDF._place`):

    voxel data   root -> pointer(64^3) -> pointer(16^3) -> dense(8^3) -> {tsdf, weight[, rgb]}
    frame blocks root -> pointer(64^3) -> bitmasked(16^3) -> touched        (one cell per block)

* A *block* is 8^3 voxels (the dense leaf), allocated only when a depth ray passes within the
  truncation band of it. The two pointer levels give a virtual range of 64*16 = 1024 blocks =
  8192 voxels per axis (82 m at 1 cm voxels) for ~2 MB of top-level pointers; a second-level
  chunk (16^3 block pointers, 32 KB) is allocated on first use.
* Voxel index ``ijk`` (may be negative) has centre ``(ijk + 0.5) * voxel_size`` in the world frame
  and lives at field index ``ijk + OFFSET``; block index ``b = floor(ijk / 8)``.
* ``touched`` marks the blocks that the current frame's rays activated; it is cleared after
  every frame. Only those blocks are integrated (as Open3D's VoxelBlockGrid does), so a frame
  costs time in proportion to the surface it sees, not to the size of the map.

Determinism: block activation is idempotent and every voxel is updated by exactly one thread per
frame, so the volume after any sequence of frames is bitwise reproducible (no float atomics).
"""


import numpy as np
import taichi as ti

BLOCK = 8  # voxels per block edge (dense leaf)
L1 = 64  # top pointer level, blocks^(1/3) per cell ... (L1 * L2 blocks per axis in all)
L2 = 16  # second pointer level
BLOCKS_PER_AXIS = L1 * L2
VOXELS_PER_AXIS = BLOCKS_PER_AXIS * BLOCK
OFFSET = VOXELS_PER_AXIS // 2  # voxel ijk is stored at field index ijk + OFFSET
BLOCK_OFFSET = OFFSET // BLOCK
CACHE_SIZE = 1 << 16


@ti.data_oriented
class SparseTSDF:
    """A sparse TSDF volume with projective weighted-average integration.

    Args:
        voxel_size: voxel edge, metres.
        trunc_m: truncation ``tau_b``, metres; the stored value is ``tsdf = min(1, sdf / tau_b)``
            (dimensionless, in [-1, 1]) for voxels with ``sdf >= -tau_b``.
        max_weight: cap of the running weight (each observation adds 1).
        with_color: also keep a weighted-average RGB per voxel.

    ``ti.init`` must have been called before construction (fields are placed here).
    """

    def __init__(self, voxel_size: float, trunc_m: float, max_weight: float = 1e4,
                 with_color: bool = False):
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.max_weight = float(max_weight)
        self.with_color = bool(with_color)
        self.block_size_m = self.voxel_size * BLOCK
        self._place()
        # Scalars written by kernels: [0] rays outside the index range, [1] voxels updated.
        self.counters = ti.field(ti.i64, shape=2)
        self._no_rgb = np.zeros((1, 1, 3), np.uint8)

    # -- fields ----------------------------------------------------------------------------
    def _place(self):
        self.tsdf = ti.field(ti.f32)
        self.weight = ti.field(ti.f32)
        self.rgb = ti.Vector.field(3, ti.f32) if self.with_color else None
        # Frame number that last touched a block; writing it allocates the block.
        self.block_stamp = ti.field(ti.i32)
        top = ti.root.pointer(ti.ijk, L1)
        self.block_ptr = top.pointer(ti.ijk, L2)  # one cell per 8^3 block
        self.block_ptr.place(self.block_stamp)
        voxels = self.block_ptr.dense(ti.ijk, BLOCK)
        if self.with_color:
            voxels.place(self.tsdf, self.weight, self.rgb)
        else:
            voxels.place(self.tsdf, self.weight)
        # Blocks touched by the current frame, as a compact list (unique entries).
        self.frame_blocks = ti.Vector.field(3, ti.i32)
        self.frame_blocks_cap = 1 << 18
        ti.root.dense(ti.i, self.frame_blocks_cap).place(self.frame_blocks)
        self.n_frame_blocks = ti.field(ti.i32, shape=())
        # Direct-mapped cache in front of the sparse stamps: most samples of a frame hit a block
        # an earlier sample already touched; the cache answers that with one dense load.
        # Entries are (frame << 30 | block key); races only cause a redundant (idempotent) check.
        self.cache = ti.field(ti.i64, shape=CACHE_SIZE)
        self.frame_id = 0

    # -- per-frame kernels -----------------------------------------------------------------
    @ti.func
    def _back_project(self, u: ti.f32, v: ti.f32, z: ti.f32, intr: ti.math.vec4, T: ti.math.mat4):
        """World point of pixel (u, v) at camera depth z: p_W = T_W_C @ (z K^-1 [u, v, 1])."""
        p_C = ti.Vector([(u - intr[2]) / intr[0] * z, (v - intr[3]) / intr[1] * z, z, 1.0])
        return (T @ p_C).xyz

    @ti.func
    def _touch(self, blk, frame: ti.i32):
        """Allocate block ``blk`` and append it to the frame's block list, once per frame."""
        key = (blk[0] << 20) | (blk[1] << 10) | blk[2]
        tag = (ti.cast(frame, ti.i64) << 30) | ti.cast(key, ti.i64)
        slot = ti.cast((ti.cast(key, ti.u32) * ti.u32(2654435761)) >> ti.u32(16), ti.i32)
        if self.cache[slot] != tag:
            self.cache[slot] = tag
            # atomic_max returns the previous stamp: exactly one thread sees it below `frame`.
            if ti.atomic_max(self.block_stamp[blk], frame) < frame:
                n = ti.atomic_add(self.n_frame_blocks[None], 1)
                if n < self.frame_blocks_cap:
                    self.frame_blocks[n] = blk

    @ti.kernel
    def _activate(self, depth: ti.types.ndarray(dtype=ti.f32, ndim=2), intr: ti.math.vec4,
                  T_W_C: ti.math.mat4, stride: ti.i32, frame: ti.i32):
        """Touch every block that a ray segment [d - tau_b, d + tau_b] of a valid pixel passes.
        The segment is sampled every half block, so no block it crosses by more than a corner is
        missed. The block list is unique but in thread order; the integration does not depend on
        that order."""
        H, W = depth.shape[0], depth.shape[1]
        step_m = 0.5 * self.block_size_m
        for vs, us in ti.ndrange((H + stride - 1) // stride, (W + stride - 1) // stride):
            v, u = vs * stride, us * stride
            d = depth[v, u]
            if d > 0:
                z0 = ti.max(d - self.trunc_m, 1e-3)
                z1 = d + self.trunc_m
                a = self._back_project(ti.f32(u), ti.f32(v), z0, intr, T_W_C)
                b = self._back_project(ti.f32(u), ti.f32(v), z1, intr, T_W_C)
                n = ti.cast(ti.ceil((b - a).norm() / step_m), ti.i32) + 1
                for s in range(n + 1):
                    x = a + (b - a) * (s / n)
                    blk = ti.cast(ti.floor(x / self.block_size_m), ti.i32) + BLOCK_OFFSET
                    if (blk >= 0).all() and (blk < BLOCKS_PER_AXIS).all():
                        self._touch(blk, frame)
                    else:
                        ti.atomic_add(self.counters[0], 1)

    @ti.kernel
    def _integrate(self, depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                   rgb: ti.types.ndarray(dtype=ti.u8, ndim=3), intr: ti.math.vec4,
                   T_C_W: ti.math.mat4):
        """Projective weighted-average update of every voxel of the frame's touched blocks:
        sdf = D(u) - z_C; observed if sdf >= -tau_b; tsdf = min(1, sdf / tau_b);
        tsdf <- (W tsdf + tsdf_new) / (W + 1), W <- min(W + 1, max_weight).
        One thread per block, each voxel written once: deterministic."""
        H, W = depth.shape[0], depth.shape[1]
        R = ti.Matrix([[T_C_W[r, c] for c in range(3)] for r in range(3)])
        t_CW = ti.Vector([T_C_W[0, 3], T_C_W[1, 3], T_C_W[2, 3]])
        for n in range(self.n_frame_blocks[None]):
            base = self.frame_blocks[n] * BLOCK
            # Camera coordinates of the block's first voxel centre and the per-voxel steps.
            x0_W = (ti.cast(base - OFFSET, ti.f32) + 0.5) * self.voxel_size
            x0_C = R @ x0_W + t_CW
            step = R * self.voxel_size  # column c = camera-frame step of +1 along world axis c
            n_updated = 0
            for t in range(BLOCK * BLOCK * BLOCK):
                a, b, c = t // (BLOCK * BLOCK), (t // BLOCK) % BLOCK, t % BLOCK
                x_C = x0_C + step @ ti.Vector([ti.f32(a), ti.f32(b), ti.f32(c)])
                if x_C.z > 1e-6:
                    inv_z = 1.0 / x_C.z
                    u = ti.cast(ti.round(intr[0] * x_C.x * inv_z + intr[2]), ti.i32)
                    v = ti.cast(ti.round(intr[1] * x_C.y * inv_z + intr[3]), ti.i32)
                    if 0 <= u < W and 0 <= v < H:
                        d = depth[v, u]
                        sdf = d - x_C.z
                        if d > 0 and sdf >= -self.trunc_m:
                            I = base + ti.Vector([a, b, c])
                            obs = ti.min(1.0, sdf / self.trunc_m)
                            w = self.weight[I]
                            self.tsdf[I] = (w * self.tsdf[I] + obs) / (w + 1.0)
                            if ti.static(self.with_color):
                                col = ti.Vector([rgb[v, u, 0], rgb[v, u, 1], rgb[v, u, 2]], ti.f32)
                                self.rgb[I] = (w * self.rgb[I] + col) / (w + 1.0)
                            self.weight[I] = ti.min(w + 1.0, self.max_weight)
                            n_updated += 1
            ti.atomic_add(self.counters[1], n_updated)

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
                  rgb=None, activation_stride: int = 1) -> int:
        """Fuse one frame; return the number of voxel updates it made.

        Args:
            depth_m: (H, W) float32 C-contiguous depth in metres, invalid pixels 0.
            K: (3, 3) pinhole intrinsics.
            T_W_C: (4, 4) camera-to-world pose.
            rgb: optional (H, W, 3) uint8, used when the volume was built ``with_color``.
            activation_stride: activate blocks from every n-th pixel in u and v (1 = all pixels).
        Inputs are trusted (validated by the caller).
        """
        intr = ti.math.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        T = np.asarray(T_W_C, dtype=np.float64)
        T_C_W = np.linalg.inv(T)
        before = int(self.counters[1])
        self.frame_id += 1
        self.n_frame_blocks[None] = 0
        self._activate(depth_m, intr, ti.math.mat4(T.astype(np.float32)), int(activation_stride),
                       self.frame_id)
        n_blocks = int(self.n_frame_blocks[None])
        if n_blocks > self.frame_blocks_cap:
            raise MemoryError(f"a frame touched {n_blocks} blocks, more than the per-frame list "
                              f"holds ({self.frame_blocks_cap}); use a larger voxel size")
        rgb_arr = rgb if (self.with_color and rgb is not None) else self._no_rgb
        self._integrate(depth_m, rgb_arr, intr, ti.math.mat4(T_C_W.astype(np.float32)))
        return int(self.counters[1]) - before

    # -- export ----------------------------------------------------------------------------
    @ti.kernel
    def _count_observed(self) -> ti.i32:
        n = 0
        for I in ti.grouped(self.weight):
            if self.weight[I] > 0:
                n += 1
        return n

    @ti.kernel
    def _export(self, ijk: ti.types.ndarray(dtype=ti.i32, ndim=2),
                tsdf: ti.types.ndarray(dtype=ti.f32, ndim=1),
                weight: ti.types.ndarray(dtype=ti.f32, ndim=1),
                rgb: ti.types.ndarray(dtype=ti.f32, ndim=2)):
        """Write observed voxels in arbitrary (thread-dependent) order; the caller sorts."""
        cursor = 0
        for I in ti.grouped(self.weight):
            if self.weight[I] > 0:
                n = ti.atomic_add(cursor, 1)
                for c in ti.static(range(3)):
                    ijk[n, c] = I[c] - OFFSET
                tsdf[n] = self.tsdf[I] * self.trunc_m
                weight[n] = self.weight[I]
                if ti.static(self.with_color):
                    for c in ti.static(range(3)):
                        rgb[n, c] = self.rgb[I][c]

    def export(self) -> dict:
        """All observed voxels (weight > 0), sorted by (i, j, k):
        ``ijk`` (N, 3) int32, ``tsdf`` (N,) float32 in metres (clamped to [-tau_b, tau_b]),
        ``weight`` (N,) float32, and ``rgb`` (N, 3) float32 0..255 if the volume has colour."""
        n = int(self._count_observed())
        ijk = np.zeros((n, 3), np.int32)
        tsdf = np.zeros(n, np.float32)
        weight = np.zeros(n, np.float32)
        rgb = np.zeros((n if self.with_color else 1, 3), np.float32)
        if n:
            self._export(ijk, tsdf, weight, rgb)
        order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
        out = {"ijk": ijk[order], "tsdf": tsdf[order], "weight": weight[order]}
        if self.with_color:
            out["rgb"] = rgb[order]
        return out

    @ti.kernel
    def _count_blocks(self) -> ti.i32:
        n = 0
        for I in ti.grouped(self.block_stamp):
            n += 1
        return n

    def stats(self) -> dict:
        """Allocated blocks, and rays (samples) that fell outside the index range."""
        return {"blocks": int(self._count_blocks()), "out_of_range_samples": int(self.counters[0])}
