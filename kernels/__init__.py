"""Taichi kernels and sparse fields of bftaichi.

This package imports only ``taichi`` and ``numpy`` (never ``bftaichi``), so other Taichi programs
can embed it: ``import kernels``. It never calls ``ti.init``; the embedding program (or
``bftaichi.init``) does, before any class here allocates fields.

Modules, one per concern (DESIGN.md section 3):
    tsdf     -- sparse projective TSDF volume (8^3-voxel blocks under a pointer-SNode block map).
    lookup   -- voxel -> band index lookup (sorted block keys + per-block tables).
    band     -- narrow band: core, dilation, compaction, 27-point neighbour tables.
    observe  -- depth frames -> SDF samples -> data term accumulated in the 27-point stencil.
    prior    -- GMRF membrane prior and anchors added into the stencil.
    pcg      -- matrix-free stencil Q·x, Jacobi PCG, batched probe variance.
    raycast  -- predicted depth of the posterior mean through the band; NBV coverage grid.
    embed    -- SDFField: the band in Taichi fields with @ti.func sdf/grad/sigma for user kernels.
"""

from .embed import SDFField
from .tsdf import SparseTSDF

__all__ = ["SDFField", "SparseTSDF"]
