"""Taichi kernels and sparse fields of bftaichi.

This package imports only ``taichi`` and ``numpy`` (never ``bftaichi``), so other Taichi programs
can embed it: ``import kernels``. It never calls ``ti.init``; the embedding program (or
``bftaichi.init``) does, before any class here allocates fields.

Modules, one per concern (DESIGN.md section 3):
    layout   -- shared constants, numpy only: block size, block-key packing, stencil offsets.
    funcs    -- shared @ti.func helpers: floor, block keys and search, cell corners, trilinear.
    tsdf     -- sparse projective TSDF volume (8^3-voxel blocks under a pointer-SNode block map).
    lookup   -- voxel -> band index lookup (sorted block keys + per-block tables) and its inverse.
    band     -- narrow band: core, dilation, compaction, 27-point neighbour tables.
    observe  -- Observer: depth frames -> SDF samples -> data term in the 27-point stencil.
    carve    -- FreeSpaceCounter: per band voxel, the frames that saw it as free space.
    dataterm -- the Taichi kernels behind Observer (normals, samples, fixed-point accumulation).
    prior    -- GMRF membrane and curvature priors and anchors added into the stencil.
    stencil  -- the stencil contract and its checks; matrix-free Q·x (27-point gather).
    compact  -- CompactStencil: the compact layout for fast single-vector Q·x.
    pcg      -- Jacobi PCG: the MAP solve and the batched multi-right-hand-side solver.
    probes   -- probe vectors (Rademacher, lattice colouring) and the probe variance.
    rays     -- ray geometry shared by raycast and coverage (pixel rays in grid coordinates).
    raycast  -- predicted depth (and its sigma) of the posterior mean through the band.
    coverage -- CoverageGrid: the seen / unknown cells of next-best-view planning.
    embed    -- SDFField: the band in Taichi fields with @ti.func sdf/grad/sigma for user kernels.
    launch   -- a shorter launch path for kernels called with numpy arrays (install()).
"""

__all__ = ["SDFField", "SparseTSDF"]


def __getattr__(name: str):
    """``kernels.SDFField`` / ``kernels.SparseTSDF``, imported on first use, so that the
    numpy-only :mod:`kernels.layout` can be imported without Taichi."""
    if name == "SDFField":
        from .embed import SDFField
        return SDFField
    if name == "SparseTSDF":
        from .tsdf import SparseTSDF
        return SparseTSDF
    raise AttributeError(f"module 'kernels' has no attribute {name!r}")
