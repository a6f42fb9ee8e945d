"""Sparse projective TSDF (Curless & Levoy), the bootstrap of BayesFusion-SDF (DESIGN.md 3.1).

Layout::

    block map    root -> pointer(4096 volumes) -> pointer(64^3) -> pointer(16^3)
                      -> {block_slot i32, block_stamp i32}            (one cell per 8^3 block)
    voxel pool   ndarrays tsdf (S*512,) i64, weight (S*512,) i32 [, rgb (S*512, 4) i32]
                 (integer sums: fixed-point observations, their count, RGB sums and count)
    slot table   ndarray slot_block (S, 3) i32: block index of the block in each pool slot
    frame list   ndarray frame_list (F, 4) i32: (map block index, slot) of each touched block
    block cache  ndarray cache (65536,) i64: direct-mapped "already listed this frame" cache

* A *block* is 8^3 voxels. Block index ``b = floor(ijk / 8)``; voxel ``ijk`` (may be negative)
  has centre ``(ijk + 0.5) * voxel_size`` in the frame of the poses it is given (a caller with
  far-away poses moves them into a local frame first: bftaichi.geometry.local_origin).
* The *block map* is a sparse Taichi SNode tree: below a per-volume pointer, two pointer levels
  give a virtual range of 64 * 16 = 1024 blocks (``layout.MAP_BLOCKS``; 8192 voxels, 82 m at
  1 cm voxels) per axis, centred on the origin (block ``b`` sits at map index ``b + 512``);
  activation samples outside it are dropped and counted. A volume's top level
  (64^3 pointers, 2 MB) is allocated when it first touches a block, a 16^3 chunk of block cells
  when a ray first reaches it. A block cell holds the block's *slot* (1-based, 0 = none yet)
  and the number of the last frame that touched the block.
* The voxels of the block in (0-based) slot ``s`` live at ``s * 512 + t`` of the dense *pool*,
  ``t = 64 a + 8 b + c`` for voxel ``8 b_ijk + (a, b, c)``. A block is thus two contiguous runs
  (tsdf 4 KB, weight 2 KB): the integration streams dense memory and looks the sparse map up
  once per block and frame, never per voxel. The pool grows by doubling (one copy) when a frame
  allocates more blocks than it holds; the sparse map never moves.
* All volumes of a Taichi program share one block-map tree (one slice per volume) and the
  kernels are module-level functions whose inputs are arguments (voxel size, truncation and
  weight cap arrive in a per-frame parameter vector), so a new volume compiles nothing and
  Taichi's offline cache serves every later run. The tree is rebuilt after ``ti.init``.
* A frame is one kernel launch, :func:`_integrate_frame`: it lists the blocks the frame's rays
  touch (:func:`_activate_row`; unique, new blocks get a slot), then updates every voxel of the
  listed blocks (:func:`_integrate_block`). Only those blocks are visited (as Open3D's
  VoxelBlockGrid does), so a frame costs time in proportion to the surface it sees, not to the
  size of the map. If the frame list or the pool turn out too small, the kernel integrates
  nothing; the caller grows them and repeats the frame under a new frame number.

Cost (7-Scenes redkitchen, 640x480, 2 cm voxels: ~690 blocks = 353k voxel visits per frame,
activation from every 4th pixel; tools/bench_tsdf.py): keeping the voxels in a dense pool made
the integration ~2x faster than storing them in the pointer SNode's leaves (a sparse lookup with
activation checks on every voxel access). Per voxel what remains is the projection (one float
division, ~15 cycles) and cache misses on the depth image (a third to a half of the time); per
frame, the activation (~1 ms) and ~0.4 ms of launch cost (Taichi's Python argument handling and
the thread-pool wake-up of the two parallel loops). Measured and not kept: a branch-free voxel
update, a non-unrolled voxel loop, parallelising over voxel rows, a 4x4-tiled depth copy, a
full-image prefetch pass, smaller block caches, other loop chunk sizes (all slower or equal).
Not tried: culling whole blocks, since only ~4 % of the listed blocks have no observed voxel.

Determinism: block activation is idempotent and every voxel is updated by exactly one thread per
frame, so the voxel values after any sequence of frames are bitwise reproducible (no float
atomics). Slot numbers and the frame-list order depend on thread scheduling; they never reach
the output (:meth:`SparseTSDF.export` sorts by ``ijk``).
"""


import numpy as np
import taichi as ti
from taichi.lang import impl

from .funcs import floor_i32
from .layout import BLOCK, BLOCK_VOXELS, MAP_BLOCKS, column_max, column_min
from .stencil import first_chunk, virtual_iterations
MAX_VOLUMES = 1 << 12  # volumes per Taichi program (ids are not reused)
L1 = 64  # first spatial pointer level: cells per axis
L2 = MAP_BLOCKS // L1  # second spatial pointer level: blocks per axis in one first-level cell
BLOCKS_PER_AXIS = L1 * L2
BLOCK_OFFSET = BLOCKS_PER_AXIS // 2  # block b is stored at map index b + BLOCK_OFFSET
CACHE_BITS = 16  # the block cache has 2^16 entries (512 KB)
FIRST_POOL_BLOCKS = 1024  # initial pool capacity in blocks (2 MB per float field)
FIRST_LIST_BLOCKS = 4096  # initial frame-list capacity in blocks

# Per-frame parameters, one float64 vector (a single cheap kernel argument):
P_A = 0  # 9: A = K R_CW * voxel_size, row-major; K x_C of voxel ijk = A ijk + c
P_C = 9  # 3: c = K (R_CW (0.5 voxel_size) (1, 1, 1) + t_CW)
P_M = 12  # 9: M = R_WC K^-1 / block_size, row-major; pixel (u, v) at depth z is in the
P_O = 21  # 3:    block at floor(o + z M (u, v, 1)), o = t_WC / block_size
P_TRUNC = 24  # truncation tau_b, metres
P_SCALE = 25  # TSDF_ONE / tau_b: a signed distance (m) to the fixed-point unit
P_STEP = 26  # activation sample spacing along a ray, blocks
P_RGB = 27  # 1 if the frame has colour (volumes with colour only)
N_PARAMS = 28
TSDF_BITS = 20
TSDF_ONE = 1 << TSDF_BITS  # fixed point: tsdf 1.0 (= tau_b) is 2^20 (~1e-6 tau_b resolution)
# Integer counters of a volume (int64 vector shared with the kernels):
C_OUT = 0  # activation samples outside the block map's index range (all frames)
C_LISTED = 1  # blocks listed by the current frame (may exceed the list capacity)
C_SLOTS = 2  # allocated blocks = used pool slots
C_UPDATES = 3  # voxel updates (all frames)
N_COUNTS = 4


class _BlockMap:
    """The sparse block map shared by all volumes of one Taichi program."""

    def __init__(self):
        self.slot = ti.field(ti.i32)  # 1-based pool slot of the block, 0 = unallocated
        self.stamp = ti.field(ti.i32)  # last frame (of its volume) that listed the block
        fb = ti.FieldsBuilder()
        fb.pointer(ti.l, MAX_VOLUMES).pointer(ti.ijk, L1).pointer(ti.ijk, L2).place(
            self.slot, self.stamp)
        self.tree = fb.finalize()
        self.prog = impl.get_runtime().prog
        self.next_volume = 0


_MAP = None


def _block_map() -> _BlockMap:
    """The block map of the current Taichi program (rebuilt after ti.init / ti.reset)."""
    global _MAP
    prog = impl.get_runtime().prog
    if prog is None:
        raise RuntimeError("Taichi is not initialised: call ti.init (or bftaichi.init) before "
                           "creating a SparseTSDF")
    if _MAP is None or _MAP.prog is not prog:
        _MAP = _BlockMap()
    return _MAP


# -- kernels ---------------------------------------------------------------------------------

@ti.func
def _touch(blk, vid: ti.i32, frame: ti.i32, slot_map: ti.template(), stamp_map: ti.template(),
           cache: ti.types.ndarray(), counts: ti.types.ndarray(),
           frame_list: ti.types.ndarray()):
    """List map block ``blk`` of volume ``vid`` once per frame; give a new block a pool slot."""
    key = (blk[0] << 20) | (blk[1] << 10) | blk[2]
    tag = (ti.cast(frame, ti.i64) << 30) | ti.cast(key, ti.i64)
    h = ti.cast((ti.cast(key, ti.u32) * ti.u32(2654435761)) >> ti.u32(32 - CACHE_BITS), ti.i32)
    if cache[h] != tag:  # a race here only costs a redundant (idempotent) check below
        cache[h] = tag
        # atomic_max returns the previous stamp: exactly one thread per frame sees it below
        # `frame`, so only that thread reads/assigns the slot (no race on the slot cell).
        if ti.atomic_max(stamp_map[blk, vid], frame) < frame:
            s = slot_map[blk, vid]
            if s == 0:
                s = ti.cast(ti.atomic_add(counts[C_SLOTS], 1), ti.i32) + 1
                slot_map[blk, vid] = s
            n = ti.atomic_add(counts[C_LISTED], 1)
            if n < frame_list.shape[0]:
                for c in ti.static(range(3)):
                    frame_list[n, c] = blk[c]
                frame_list[n, 3] = s - 1


@ti.func
def _activate_row(vs: ti.i32, depth: ti.template(), prm: ti.template(), stride: ti.i32,
                  frame: ti.i32, vid: ti.i32, slot_map: ti.template(), stamp_map: ti.template(),
                  cache: ti.template(), counts: ti.template(), frame_list: ti.template()):
    """Activation of pixel row ``vs * stride``: list every block that the ray segment
    [d - tau_b, d + tau_b] of a valid pixel (every ``stride``-th in the row) passes. The
    segment is sampled at n + 1 evenly spaced points, n = ceil(length / step) + 1 with step
    ``prm[P_STEP]`` = half a block (4 samples on a block-long segment, like the 4 of Open3D's
    compute_unique_block_coordinates), so no block it crosses by more than a corner is missed.
    Float32, incremental stepping (a per-sample division is what LLVM makes of x = a + s/n)."""
    M = ti.Matrix([[ti.cast(prm[P_M + 3 * r + c], ti.f32) for c in ti.static(range(3))]
                   for r in ti.static(range(3))])
    o = ti.cast(ti.Vector([prm[P_O], prm[P_O + 1], prm[P_O + 2]]), ti.f32)
    trunc = ti.cast(prm[P_TRUNC], ti.f32)
    inv_step = ti.cast(1.0 / prm[P_STEP], ti.f32)
    v = vs * stride
    for us in range((depth.shape[1] + stride - 1) // stride):
        u = us * stride
        d = depth[v, u]
        if d > 0:
            ray = M @ ti.Vector([ti.cast(u, ti.f32), ti.cast(v, ti.f32), 1.0])
            x = o + ti.max(d - trunc, 1e-3) * ray  # segment start, block units
            seg = o + (d + trunc) * ray - x
            n = 1 - floor_i32(-seg.norm() * inv_step)  # ceil(length / step) + 1
            delta = seg / ti.cast(n, ti.f32)
            last = ti.Vector([-1, -1, -1])
            for _ in range(n + 1):
                blk = floor_i32(x) + BLOCK_OFFSET
                if (blk >= 0).all() and (blk < BLOCKS_PER_AXIS).all():
                    if (blk != last).any():  # consecutive samples often share a block
                        last = blk
                        _touch(blk, vid, frame, slot_map, stamp_map, cache, counts, frame_list)
                else:
                    ti.atomic_add(counts[C_OUT], 1)
                x += delta


@ti.func
def _integrate_block(n: ti.i32, sign: ti.i32, depth: ti.template(), rgb: ti.template(),
                     prm: ti.template(), frame_list: ti.template(), tsdf: ti.template(),
                     weight: ti.template(), color: ti.template(), slot_block: ti.template(),
                     counts: ti.template(), with_color: ti.template()):
    """Projective update of the 512 voxels of listed block ``n`` (DESIGN.md 3.1), in integer
    sums: (u, v) = nearest pixel of K x_C = floor(K x_C / z_C + 0.5), sdf = D(u, v) - z_C;
    observed if z_C > 0, D > 0 and sdf >= -tau_b; q = floor(min(1, sdf / tau_b) * 2^20 + 1/2);
    S <- S + sign q, W <- W + sign [, rgb sums and their count likewise]. The stored TSDF is
    S / (W 2^20): the average of the observations, exact whatever their order, and a frame
    integrated with ``sign = -1`` removes exactly what it added with ``sign = +1``."""
    H, W = depth.shape[0], depth.shape[1]
    Wf, Hf = ti.cast(W, ti.f32), ti.cast(H, ti.f32)
    step_i = ti.Vector([prm[P_A], prm[P_A + 3], prm[P_A + 6]])  # K x_C step along +i
    step_j = ti.Vector([prm[P_A + 1], prm[P_A + 4], prm[P_A + 7]])
    step_k = ti.Vector([prm[P_A + 2], prm[P_A + 5], prm[P_A + 8]])
    trunc = ti.cast(prm[P_TRUNC], ti.f32)
    scale = ti.cast(prm[P_SCALE], ti.f32)  # 2^20 / tau_b: sdf (m) to fixed point
    one = ti.cast(TSDF_ONE, ti.f32)
    sign64 = ti.cast(sign, ti.i64)
    use_rgb = prm[P_RGB] > 0
    slot = frame_list[n, 3]
    blk = ti.Vector([frame_list[n, 0], frame_list[n, 1], frame_list[n, 2]]) - BLOCK_OFFSET
    for c in ti.static(range(3)):
        slot_block[slot, c] = blk[c]
    # K x_C of the block's first voxel centre, in float64 (large terms cancel); the per-voxel
    # steps from it are small and stay in float32.
    base = ti.cast(blk * BLOCK, ti.f64)
    p_blk = ti.cast(step_i * base[0] + step_j * base[1] + step_k * base[2]
                    + ti.Vector([prm[P_C], prm[P_C + 1], prm[P_C + 2]]), ti.f32)
    di, dj, dk = ti.cast(step_i, ti.f32), ti.cast(step_j, ti.f32), ti.cast(step_k, ti.f32)
    first = slot * BLOCK_VOXELS
    n_obs = 0
    for ab in range(BLOCK * BLOCK):
        p_row = p_blk + di * ti.cast(ab // BLOCK, ti.f32) + dj * ti.cast(ab % BLOCK, ti.f32)
        for c in ti.static(range(BLOCK)):  # unrolled: ~15 % faster than a loop
            p = p_row + dk * float(c)
            z = p[2]
            if z > 0:
                inv_z = 1.0 / z
                # Nearest pixel = floor(x + 0.5): bounds are checked in float first, so the
                # integer conversion (truncation toward zero) equals floor.
                uh = p[0] * inv_z + 0.5
                vh = p[1] * inv_z + 0.5
                if uh >= 0 and uh < Wf and vh >= 0 and vh < Hf:
                    u = ti.cast(uh, ti.i32)
                    v = ti.cast(vh, ti.i32)
                    d = depth[v, u]
                    sdf = d - z
                    if d > 0 and sdf >= -trunc:
                        i = first + ab * BLOCK + c
                        q = ti.floor(ti.min(one, sdf * scale) + 0.5)  # nearest integer
                        # plain read-modify-write: one thread owns the voxel (Taichi would make
                        # `+=` an atomic add, ~25 % slower here)
                        tsdf[i] = tsdf[i] + sign64 * ti.cast(q, ti.i64)
                        weight[i] = weight[i] + sign
                        if ti.static(with_color):
                            if use_rgb:
                                for k in ti.static(range(3)):
                                    color[i, k] = color[i, k] + sign * ti.cast(rgb[v, u, k], ti.i32)
                                color[i, 3] = color[i, 3] + sign
                        n_obs += 1
    ti.atomic_add(counts[C_UPDATES], n_obs)


@ti.kernel
def _integrate_frame(depth: ti.types.ndarray(dtype=ti.f32, ndim=2),
                     rgb: ti.types.ndarray(dtype=ti.u8, ndim=3),
                     prm: ti.types.ndarray(dtype=ti.f64, ndim=1), stride: ti.i32, frame: ti.i32,
                     sign: ti.i32, vid: ti.i32, slot_map: ti.template(), stamp_map: ti.template(),
                     cache: ti.types.ndarray(dtype=ti.i64, ndim=1),
                     counts: ti.types.ndarray(dtype=ti.i64, ndim=1),
                     frame_list: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     tsdf: ti.types.ndarray(dtype=ti.i64, ndim=1),
                     weight: ti.types.ndarray(dtype=ti.i32, ndim=1),
                     color: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     slot_block: ti.types.ndarray(dtype=ti.i32, ndim=2),
                     with_color: ti.template()):
    """One frame in one launch: (1) activation, parallel over pixel rows (:func:`_activate_row`);
    (2) if the frame list and the pool were large enough, integration, parallel over the listed
    blocks (:func:`_integrate_block`); otherwise nothing is integrated and the caller grows
    them and calls again with a new frame number.

    ``sign`` +1 adds the frame, -1 removes a frame added before with the same depth and pose.

    Determinism: atomics only on integer counters and block stamps, so the listed *set* of
    blocks is deterministic (its order is not); each voxel is updated by the one thread of its
    block, in integers: the voxel values are bitwise reproducible, and independent of the order
    of the frames."""
    counts[C_LISTED] = 0
    # both loops deal their rows / blocks out over at least TASK_MIN iterations per thread
    # (kernels.stencil.first_chunk): a loop over fewer runs on one thread
    n_rows = (depth.shape[0] + stride - 1) // stride
    n_virtual = ti.max(n_rows, ti.static(virtual_iterations()))
    for t in range(n_virtual):
        for vs in range(first_chunk(t, n_rows, n_virtual), first_chunk(t + 1, n_rows, n_virtual)):
            _activate_row(vs, depth, prm, stride, frame, vid, slot_map, stamp_map, cache,
                          counts, frame_list)
    n_blocks = ti.cast(counts[C_LISTED], ti.i32)
    if (n_blocks > frame_list.shape[0]
            or counts[C_SLOTS] * BLOCK_VOXELS > ti.cast(tsdf.shape[0], ti.i64)):
        n_blocks = 0
    n_virtual_b = ti.max(n_blocks, ti.static(virtual_iterations()))
    for t in range(n_virtual_b):
        for n in range(first_chunk(t, n_blocks, n_virtual_b),
                       first_chunk(t + 1, n_blocks, n_virtual_b)):
            _integrate_block(n, sign, depth, rgb, prm, frame_list, tsdf, weight, color,
                             slot_block, counts, with_color)


@ti.kernel
def _load_blocks(blocks: ti.types.ndarray(dtype=ti.i32, ndim=2), frame: ti.i32, vid: ti.i32,
                 slot_map: ti.template(), stamp_map: ti.template(),
                 cache: ti.types.ndarray(dtype=ti.i64, ndim=1),
                 counts: ti.types.ndarray(dtype=ti.i64, ndim=1),
                 frame_list: ti.types.ndarray(dtype=ti.i32, ndim=2),
                 slot_block: ti.types.ndarray(dtype=ti.i32, ndim=2)):
    """Allocate (or find) the map blocks ``blocks`` (n, 3) (block indices) and list them in
    ``frame_list`` with their pool slot, as a frame's activation does."""
    counts[C_LISTED] = 0
    for n in range(blocks.shape[0]):
        blk = ti.Vector([blocks[n, 0], blocks[n, 1], blocks[n, 2]]) + BLOCK_OFFSET
        _touch(blk, vid, frame, slot_map, stamp_map, cache, counts, frame_list)
    for n in range(ti.min(ti.cast(counts[C_LISTED], ti.i32), frame_list.shape[0])):
        for c in ti.static(range(3)):
            slot_block[frame_list[n, 3], c] = frame_list[n, c] - BLOCK_OFFSET


@ti.kernel
def _copy_rows(src: ti.types.ndarray(), dst: ti.types.ndarray(), n: ti.i32):
    """dst[i, ...] = src[i, ...] for i < n (used to grow the pool)."""
    for I in ti.grouped(src):
        if I[0] < n:
            dst[I] = src[I]


# -- the volume ------------------------------------------------------------------------------

class SparseTSDF:
    """A sparse TSDF volume with projective averaging, kept as integer sums.

    Args:
        voxel_size: voxel edge, metres.
        trunc_m: truncation ``tau_b``, metres; each observation is ``min(1, sdf / tau_b)``
            (dimensionless, in [-1, 1]) for voxels with ``sdf >= -tau_b``, and a voxel's TSDF is
            the mean of its observations.
        max_weight: cap of the *exported* weight (each observation counts 1). The mean itself is
            never capped: a capped running average cannot give a frame back exactly.
        with_color: also keep the mean RGB per voxel (over the frames that had colour).

    Storage: per voxel the sum of the observations in fixed point (int64, 2^20 per tau_b) and
    their count (int32) [and, with colour, int32 sums of R, G, B and the count of coloured
    observations]: 12 bytes a voxel (20 with colour). Integer sums make integration
    order-independent and :meth:`integrate` with ``sign=-1`` subtract a frame exactly
    (issue 19: pose updates without re-fusing).

    ``ti.init`` must have been called before construction. All volumes of a program share the
    compiled kernels; constructing one costs no compilation.
    """

    def __init__(self, voxel_size: float, trunc_m: float, max_weight: float = 1e4,
                 with_color: bool = False):
        self.voxel_size = float(voxel_size)
        self.trunc_m = float(trunc_m)
        self.max_weight = float(max_weight)
        self.with_color = bool(with_color)
        self.block_size_m = self.voxel_size * BLOCK
        self._map = _block_map()
        if self._map.next_volume >= MAX_VOLUMES:
            raise RuntimeError(f"more than {MAX_VOLUMES} SparseTSDF volumes in one Taichi "
                               f"program; call ti.reset() or ti.init() to start over")
        self.volume_id = self._map.next_volume
        self._map.next_volume += 1
        self.frame_id = 0
        self.counts = np.zeros(N_COUNTS, np.int64)
        self._params = np.zeros(N_PARAMS, np.float64)
        self._no_rgb = np.zeros((1, 1, 3), np.uint8)
        self._cache = ti.ndarray(ti.i64, shape=(1 << CACHE_BITS,))
        self.frame_list = ti.ndarray(ti.i32, shape=(FIRST_LIST_BLOCKS, 4))
        self.pool_blocks = 0
        self.tsdf = self.weight = self.rgb = self.slot_block = None
        self._grow_pool(FIRST_POOL_BLOCKS)

    def _grow_pool(self, min_blocks: int):
        """Reallocate the pool with room for at least ``min_blocks`` blocks, keeping the data."""
        cap = max(FIRST_POOL_BLOCKS, self.pool_blocks)
        while cap < min_blocks:
            cap *= 2
        n = cap * BLOCK_VOXELS
        new = {"tsdf": ti.ndarray(ti.i64, shape=(n,)), "weight": ti.ndarray(ti.i32, shape=(n,)),
               "slot_block": ti.ndarray(ti.i32, shape=(cap, 3)),
               "rgb": ti.ndarray(ti.i32, shape=(n if self.with_color else 1, 4))}
        used = int(self.counts[C_SLOTS])
        for name, arr in new.items():
            old = getattr(self, name)
            rows = used if name == "slot_block" else used * BLOCK_VOXELS
            if old is not None and rows and (name != "rgb" or self.with_color):
                _copy_rows(old, arr, rows)
            setattr(self, name, arr)
        self.pool_blocks = cap

    def _frame_params(self, K: np.ndarray, T_W_C: np.ndarray) -> np.ndarray:
        """The per-frame parameter vector (see P_*), float64."""
        K = np.asarray(K, np.float64)
        T = np.asarray(T_W_C, np.float64)
        R_WC, t_WC = T[:3, :3], T[:3, 3]
        prm = self._params
        prm[P_A:P_A + 9], prm[P_C:P_C + 3] = voxel_projection(K, T, self.voxel_size)
        K_inv = np.array([[1.0 / K[0, 0], 0.0, -K[0, 2] / K[0, 0]],
                          [0.0, 1.0 / K[1, 1], -K[1, 2] / K[1, 1]], [0.0, 0.0, 1.0]])
        prm[P_M:P_M + 9] = (R_WC @ K_inv / self.block_size_m).ravel()
        prm[P_O:P_O + 3] = t_WC / self.block_size_m
        prm[P_TRUNC] = self.trunc_m
        prm[P_SCALE] = TSDF_ONE / self.trunc_m
        prm[P_STEP] = 0.5
        return prm

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_W_C: np.ndarray,
                  rgb=None, activation_stride: int = 1, sign: int = 1) -> int:
        """Fuse one frame (``sign=-1``: remove it); return the number of voxel updates it made.

        Args:
            depth_m: (H, W) float32 C-contiguous depth in metres, invalid pixels 0.
            K: (3, 3) pinhole intrinsics.
            T_W_C: (4, 4) camera-to-world pose.
            rgb: (H, W, 3) uint8 C-contiguous colour registered to the depth, used when the
                volume was built ``with_color``. A colour volume given no ``rgb`` updates only
                tsdf and weight for this frame; the colour stays the mean of the coloured ones.
            activation_stride: activate blocks from every n-th pixel in u and v (1 = all pixels).
            sign: +1 adds the frame; -1 subtracts a frame added before with the same depth,
                colour, K, pose and stride, exactly (the volume is then bitwise what it would be
                without that frame; its blocks stay allocated, their emptied voxels unexported).
        Inputs are trusted (validated by the caller; subtracting a frame never added corrupts
        the volume).
        """
        use_color = self.with_color and rgb is not None
        prm = self._frame_params(K, T_W_C)
        prm[P_RGB] = 1.0 if use_color else 0.0
        counts = self.counts
        before = int(counts[C_UPDATES])
        out_before = int(counts[C_OUT])
        m = self._map
        rgb_arr = rgb if use_color else self._no_rgb
        while True:
            self.frame_id += 1
            counts[C_OUT] = out_before  # a repeated listing must not count its samples twice
            _integrate_frame(depth_m, rgb_arr, prm, int(activation_stride), self.frame_id,
                             int(sign), self.volume_id, m.slot, m.stamp, self._cache, counts,
                             self.frame_list, self.tsdf, self.weight, self.rgb, self.slot_block,
                             use_color)
            n_blocks, n_slots = int(counts[C_LISTED]), int(counts[C_SLOTS])
            if n_blocks <= self.frame_list.shape[0] and n_slots <= self.pool_blocks:
                break
            # The kernel listed more blocks than the frame list or the pool holds and integrated
            # nothing: grow them and list again under a new frame stamp (allocated blocks keep
            # their slot). Happens about log2(final / initial size) times per volume.
            if n_blocks > self.frame_list.shape[0]:
                cap = self.frame_list.shape[0]
                while cap < n_blocks:
                    cap *= 2
                self.frame_list = ti.ndarray(ti.i32, shape=(cap, 4))
            if n_slots > self.pool_blocks:
                self._grow_pool(n_slots)
        return int(counts[C_UPDATES]) - before

    # -- queries ---------------------------------------------------------------------------
    def frame_blocks(self) -> np.ndarray:
        """Block indices (n, 3) int32 that the last :meth:`integrate` listed, sorted by (i, j, k).
        Voxel ``ijk`` belongs to block ``ijk // 8``."""
        n = int(self.counts[C_LISTED])
        blk = self.frame_list.to_numpy()[:n, :3] - BLOCK_OFFSET
        return blk[_lex_order(blk)].astype(np.int32)

    def export(self) -> dict:
        """All observed voxels (weight > 0), sorted by (i, j, k):
        ``ijk`` (N, 3) int32, ``tsdf`` (N,) float32 in metres (clamped to [-tau_b, tau_b]),
        ``weight`` (N,) float32 (the number of observations, capped at ``max_weight``), and
        ``rgb`` (N, 3) float32 0..255 if the volume has colour (0 where no observation had
        colour). Values are the integer sums divided in float64, then rounded to float32."""
        n_slots = int(self.counts[C_SLOTS])
        nv = n_slots * BLOCK_VOXELS
        count = self.weight.to_numpy()[:nv]
        flat = np.flatnonzero(count > 0)
        ijk = self._voxel_ijk(flat)
        order = _lex_order(ijk)
        flat = flat[order]
        n = count[flat].astype(np.float64)
        mean = self.tsdf.to_numpy()[:nv][flat] / (n * TSDF_ONE)
        out = {"ijk": ijk[order].astype(np.int32),
               "tsdf": (mean * self.trunc_m).astype(np.float32),
               "weight": np.minimum(n, self.max_weight).astype(np.float32)}
        if self.with_color:
            sums = self.rgb.to_numpy()[:nv][flat].astype(np.float64)
            out["rgb"] = (sums[:, :3] / np.maximum(sums[:, 3:], 1)).astype(np.float32)
        return out

    def state(self) -> dict:
        """The integer sums of every observed voxel, sorted by (i, j, k): ``ijk`` (N, 3) int32,
        ``tsdf_sum`` (N,) int64 (fixed point, :data:`TSDF_ONE` per tau_b), ``count`` (N,) int32
        [, ``rgb_sum`` (N, 4) int32: R, G, B sums and the coloured count]. :meth:`load_state` of
        a new volume with the same voxel size and truncation restores it exactly."""
        nv = int(self.counts[C_SLOTS]) * BLOCK_VOXELS
        count = self.weight.to_numpy()[:nv]
        flat = np.flatnonzero(count > 0)
        ijk = self._voxel_ijk(flat)
        order = _lex_order(ijk)
        flat = flat[order]
        out = {"ijk": ijk[order].astype(np.int32), "tsdf_sum": self.tsdf.to_numpy()[:nv][flat],
               "count": count[flat]}
        if self.with_color:
            out["rgb_sum"] = self.rgb.to_numpy()[:nv][flat]
        return out

    def load_state(self, state: dict) -> None:
        """Set the voxels of :meth:`state` (into an empty volume); integration and removal then
        go on as if its frames had been integrated here."""
        if int(self.counts[C_SLOTS]):
            raise RuntimeError("load_state needs an empty volume")
        ijk = np.asarray(state["ijk"], np.int64)
        if len(ijk) == 0:
            return
        blocks = np.unique(np.floor_divide(ijk, BLOCK), axis=0).astype(np.int32)
        if len(blocks) > self.frame_list.shape[0]:
            self.frame_list = ti.ndarray(ti.i32, shape=(len(blocks), 4))
        self._grow_pool(len(blocks))
        self.frame_id += 1
        m = self._map
        _load_blocks(np.ascontiguousarray(blocks), self.frame_id, self.volume_id, m.slot,
                     m.stamp, self._cache, self.counts, self.frame_list, self.slot_block)
        slot_of = self.frame_list.to_numpy()[:len(blocks)]
        order = _lex_order(slot_of[:, :3] - BLOCK_OFFSET)  # the rows of `blocks`, sorted
        slots = slot_of[order, 3].astype(np.int64)
        b = np.searchsorted(_block_keys(blocks), _block_keys(np.floor_divide(ijk, BLOCK)))
        local = ijk - np.floor_divide(ijk, BLOCK) * BLOCK
        flat = slots[b] * BLOCK_VOXELS + (local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2])
        nv = self.pool_blocks * BLOCK_VOXELS
        for name, key, dtype, shape in (("tsdf", "tsdf_sum", np.int64, (nv,)),
                                        ("weight", "count", np.int32, (nv,)),
                                        ("rgb", "rgb_sum", np.int32, (nv, 4))):
            if name == "rgb" and not self.with_color:
                continue
            full = np.zeros(shape, dtype)
            full[flat] = state[key]
            getattr(self, name).from_numpy(full)

    def _voxel_ijk(self, flat: np.ndarray) -> np.ndarray:
        """(n, 3) int64 voxel indices of flat pool positions."""
        slot, t = flat >> 9, flat & (BLOCK_VOXELS - 1)
        return (self.slot_block.to_numpy()[:int(self.counts[C_SLOTS])].astype(np.int64)[slot]
                * BLOCK + np.stack([t >> 6, (t >> 3) & 7, t & 7], axis=1))

    def blocks(self) -> np.ndarray:
        """Block indices (n, 3) int32 of every allocated block, in slot order."""
        return self.slot_block.to_numpy()[:int(self.counts[C_SLOTS])]

    def stats(self) -> dict:
        """Allocated blocks, and activation samples that fell outside the index range."""
        return {"blocks": int(self.counts[C_SLOTS]),
                "out_of_range_samples": int(self.counts[C_OUT])}


def voxel_projection(K: np.ndarray, T_W_C: np.ndarray, voxel_size: float) -> tuple:
    """``(A, c)``: ``K x_C`` of voxel ``ijk``'s centre is ``A ijk + c``, with ``A = K R_CW
    voxel_size`` (9,) row-major and ``c = K (R_CW (0.5 voxel_size) (1, 1, 1) + t_CW)`` (3,),
    float64: how the bootstrap (and :mod:`kernels.carve`) projects voxels into a frame."""
    K = np.asarray(K, np.float64)
    T_C_W = np.linalg.inv(np.asarray(T_W_C, np.float64))  # not R^T: recorded rotations are
    R_CW, t_CW = T_C_W[:3, :3], T_C_W[:3, 3]  # orthonormal only to ~1e-6
    return ((K @ R_CW * voxel_size).ravel(),
            K @ (R_CW @ np.full(3, 0.5 * voxel_size) + t_CW))


def _block_keys(blocks: np.ndarray) -> np.ndarray:
    """Sortable int64 keys of block indices (n, 3) within the map's range."""
    b = np.asarray(blocks, np.int64) + BLOCK_OFFSET
    return (b[:, 0] * BLOCKS_PER_AXIS + b[:, 1]) * BLOCKS_PER_AXIS + b[:, 2]


def _lex_order(ijk: np.ndarray) -> np.ndarray:
    """Permutation sorting integer rows (N, 3) by (i, j, k) (one argsort of a linear key)."""
    if len(ijk) == 0:
        return np.zeros(0, np.int64)
    ijk = ijk.astype(np.int64, copy=False)
    lo = column_min(ijk)
    span = column_max(ijk) - lo + 1
    key = ((ijk[:, 0] - lo[0]) * span[1] + (ijk[:, 1] - lo[1])) * span[2] + (ijk[:, 2] - lo[2])
    return np.argsort(key, kind="stable")
