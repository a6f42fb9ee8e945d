"""Spatial chunks of the posterior solve (``run.chunk_m``, issue 20; DESIGN.md section 7).

The band is cut into cubes of ``side = 8 * round(chunk_m / (8 voxel))`` voxels (whole TSDF
blocks, at least one): chunk ``c = floor(ijk / side)``. A chunk's solve takes the bootstrap's
voxels within its core plus ``halo + 1`` voxels (the band's one-voxel dilation then reaches
``halo`` voxels around the core), builds that band, observes every frame into it (samples
outside it are dropped, as outside any band), adds the prior and solves MAP and variance as a
whole-band solve does. The voxels of its core keep their values; the halo's, which feel the
chunk's edge, are dropped. Every voxel of the whole band lies in exactly one core, and its
chunk's band holds it (the whole band's criterion applied to a superset of its neighbours), so
the stitched posterior covers the band once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Chunk", "ChunkPlan", "chunk_plan", "merge_stats"]

BLOCK = 8


@dataclass(frozen=True)
class Chunk:
    key: tuple[int, int, int]  # chunk index
    side: int  # voxels
    halo: int  # voxels

    def select(self, voxels: dict) -> dict:
        """The bootstrap's exported voxels within the core plus ``halo + 1`` voxels."""
        lo = np.array(self.key) * self.side - self.halo - 1
        hi = (np.array(self.key) + 1) * self.side + self.halo + 1
        ijk = voxels["ijk"]
        m = np.all((ijk >= lo) & (ijk < hi), axis=1)
        return {k: v[m] for k, v in voxels.items()}

    def core_in(self, chunk_ijk: np.ndarray, full_ijk: np.ndarray):
        """``(core, where)``: the mask of this chunk's band voxels that lie in its core, and
        their positions in the whole band (both bands are sorted by (i, j, k))."""
        core = np.all(np.floor_divide(chunk_ijk, self.side) == np.array(self.key), axis=1)
        keys_full, keys_core = _linear(full_ijk), _linear(chunk_ijk[core])
        where = np.searchsorted(keys_full, keys_core)
        if not np.array_equal(keys_full[np.minimum(where, len(keys_full) - 1)], keys_core):
            raise AssertionError(f"chunk {self.key}: its core voxels are not in the whole band")
        return core, where


@dataclass(frozen=True)
class ChunkPlan:
    chunks: list[Chunk]
    side: int  # voxels
    halo: int
    core_voxels: list[int]  # band voxels in each chunk's core


def chunk_plan(band_ijk: np.ndarray, chunk_m: float, voxel_size_m: float, halo: int) -> ChunkPlan:
    """The chunks whose cores hold band voxels, in (i, j, k) order."""
    side = BLOCK * max(1, int(round(chunk_m / (BLOCK * voxel_size_m))))
    keys, counts = np.unique(np.floor_divide(band_ijk, side), axis=0, return_counts=True)
    return ChunkPlan(chunks=[Chunk(tuple(int(x) for x in k), side, int(halo)) for k in keys],
                     side=side, halo=int(halo), core_voxels=[int(c) for c in counts])


def merge_stats(parts: list[dict], plan: ChunkPlan) -> dict:
    """The Posterior's scalar fields from the chunks' solves: converged only if every chunk
    converged, the worst residual and the most iterations; noise fits and counts per chunk."""
    maps = [p["solver"] for p in parts]
    worst = max(range(len(maps)), key=lambda i: maps[i].get("relative_residual", 0.0))
    solver = dict(maps[worst], converged=all(m["converged"] for m in maps),
                  iterations=max(m["iterations"] for m in maps),
                  chunks={"n": len(parts), "side_voxels": plan.side, "halo_voxels": plan.halo,
                          "core_voxels": plan.core_voxels,
                          "iterations": [m["iterations"] for m in maps],
                          "converged": [bool(m["converged"]) for m in maps]})
    variance = dict(parts[0]["variance"])
    if any("n_not_converged" in p["variance"] for p in parts):
        variance["n_not_converged"] = sum(p["variance"].get("n_not_converged", 0) for p in parts)
    observations = {k: sum(p["observations"][k] for p in parts)
                    for k, v in parts[0]["observations"].items() if isinstance(v, int)}
    observations["note"] = "summed over the chunks: samples in a halo count in two chunks"
    extra = float(np.median([p["sigma_extra_m"] for p in parts]))
    corr = float(np.median([p["sigma_corr_m"] for p in parts]))
    observations["noise_fit"] = {"sigma_extra_m": extra, "sigma_corr_m": corr,
                                 "per_chunk": [p["observations"].get("noise_fit") for p in parts]}
    return {"solver": solver, "variance": variance, "observations": observations,
            "sigma_extra_m": extra, "sigma_corr_m": corr}


def _linear(ijk: np.ndarray) -> np.ndarray:
    """Sortable int64 keys of voxel indices (lexicographic order), within +-2^20."""
    i = np.asarray(ijk, np.int64) + (1 << 20)
    return (i[:, 0] << 42) | (i[:, 1] << 21) | i[:, 2]
