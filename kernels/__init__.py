"""Taichi kernels and sparse fields of bftaichi.

This package imports only ``taichi`` and ``numpy`` (never ``bftaichi``), so other Taichi programs
can embed it: ``import kernels``. It never calls ``ti.init``; the embedding program (or
``bftaichi.init``) does, before any class here allocates fields.

Modules, one per concern:
    tsdf  -- sparse projective TSDF volume (8^3-voxel blocks under pointer SNodes).
"""

from .tsdf import SparseTSDF

__all__ = ["SparseTSDF"]
