"""Step 2 of Algorithm 1: the narrow band of unknowns around the bootstrap surface
(DESIGN.md section 3.2), compacted to ``0..N-1`` with a 27-point neighbour table.

Every later stage runs on a :class:`Band`; :func:`build_band` makes one from the bootstrap's
exported voxels, :meth:`Band.from_voxels` from a saved band (no neighbour table)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, NoSurfaceError

__all__ = ["BandConfig", "Band", "build_band"]


@dataclass
class BandConfig:
    """``[band]``: the narrow band of unknowns around the bootstrap surface (DESIGN.md 3.2)."""

    stencil: int = 26
    """Neighbours of the GMRF prior (a count, no unit): 6 (faces), 18 (+ edges) or 26
    (+ corners), weights ``1/|offset|^2``. The stored stencil has 27 points either way (the
    data term needs them), so 26 costs no extra time per Q·x."""

    def check(self) -> None:
        if self.stencil not in (6, 18, 26):
            raise ConfigError(f"band.stencil = {self.stencil} is not one of 6, 18, 26")


@dataclass(eq=False)
class Band:
    """The narrow band: N voxels in lexicographic ``(i, j, k)`` order.

    Attributes:
        ijk: (N, 3) int32 voxel indices (centre ``(ijk + 0.5) * voxel_size``).
        tsdf: (N,) float32 bootstrap TSDF, metres (the dilation voxels get the fill value).
        weight: (N,) float32 bootstrap weight (0: not observed, a dilation voxel).
        block_keys: (B,) int64 sorted block keys and ``block_table`` (B, 512) int32 band index
            per voxel of each block, -1 outside (:mod:`kernels.lookup`): voxel -> band index.
        nbr: (N, 27) int32 band index of each stencil neighbour (-1 outside), or None for a
            band read back from ``band.npz`` (planning and evaluation do not need it).
    """

    ijk: np.ndarray
    tsdf: np.ndarray
    weight: np.ndarray
    block_keys: np.ndarray
    block_table: np.ndarray
    nbr: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ijk)

    @property
    def observed(self) -> np.ndarray:
        """(N,) bool, seen by the bootstrap (weight > 0)."""
        return self.weight > 0

    @property
    def reference(self) -> np.ndarray:
        """(N,) float32 bootstrap TSDF at observed voxels, NaN elsewhere: what the side gate
        of the observations tests against (:mod:`.observe`)."""
        return np.where(self.weight > 0, self.tsdf, np.float32(np.nan))

    @classmethod
    def from_voxels(cls, ijk, tsdf, weight) -> "Band":
        """A band of known voxels (a saved ``band.npz``) with its lookup tables, no neighbour
        table."""
        from kernels.lookup import build_block_table

        ijk = np.asarray(ijk, np.int32)
        keys, table = build_block_table(ijk)
        weight = np.asarray(weight, np.float32)
        return cls(ijk=ijk, tsdf=np.asarray(tsdf, np.float32), weight=weight,
                   block_keys=keys, block_table=table)


def build_band(voxels: dict, bootstrap_trunc_m: float) -> tuple[Band, np.ndarray]:
    """The band of the bootstrap's exported ``voxels`` (``ijk, tsdf, weight``) with truncation
    ``alpha tau`` (metres), and the PCG start ``x0`` (N,) float32 (the TSDF). Raises
    NoSurfaceError when no observed voxel has ``|tsdf| < alpha tau``."""
    from kernels.band import build_band as build

    b = build(voxels["ijk"], voxels["tsdf"], voxels["weight"], bootstrap_trunc_m)
    if len(b["ijk"]) == 0:
        raise NoSurfaceError("the narrow band is empty: no observed voxel has |tsdf| below the "
                             "bootstrap truncation, so there is no surface to refine")
    band = Band(ijk=b["ijk"], tsdf=b["tsdf"], weight=b["weight"],
                block_keys=b["block_keys"], block_table=b["block_table"], nbr=b["nbr"])
    return band, b["x0"]
