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


    def frames(self, frames, voxel_size_m: float, reach_m: float, depth_max_m: float):
        """The frames (local poses) whose view can reach this chunk's voxels: its box grown by
        ``reach_m`` (the observation's reach along a ray) is not wholly behind the camera,
        beyond ``depth_max_m`` or beside the image. A frame it drops has no sample in the
        chunk, so dropping it changes nothing but the time."""
        return _Visible(frames, self, voxel_size_m, reach_m, depth_max_m)


class _Visible:
    """A frame source filtered by :meth:`Chunk.frames` (``len`` and indexing, lazily)."""

    def __init__(self, frames, chunk: Chunk, vs: float, reach: float, depth_max: float):
        lo = (np.array(chunk.key) * chunk.side - chunk.halo - 1) * vs - reach
        hi = ((np.array(chunk.key) + 1) * chunk.side + chunk.halo + 1) * vs + reach
        self.corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                 for z in (lo[2], hi[2])])
        self.source, self.depth_max = frames, depth_max + reach
        self.keep: list[int] | None = None

    def _sees(self, frame) -> bool:
        T = np.asarray(frame.T_W_C, np.float64)
        c = (self.corners - T[:3, 3]) @ T[:3, :3]  # corners in the camera frame
        z = c[:, 2]
        if np.all(z <= 0) or np.all(z > self.depth_max):
            return False
        if np.any(z <= 1e-6):  # the box straddles the camera plane: keep it
            return True
        K = np.asarray(frame.K, np.float64)
        u = K[0, 0] * c[:, 0] / z + K[0, 2]
        v = K[1, 1] * c[:, 1] / z + K[1, 2]
        h, w = frame.depth_m.shape[:2]
        return not (np.all(u < -0.5) or np.all(u > w - 0.5) or np.all(v < -0.5)
                    or np.all(v > h - 0.5))

    def _index(self) -> list[int]:
        if self.keep is None:
            self.keep = [i for i in range(len(self.source)) if self._sees(self.source[i])]
        return self.keep

    def __len__(self) -> int:
        return len(self._index())

    def __getitem__(self, i: int):
        return self.source[self._index()[i]]

    def __iter__(self):
        return (self.source[i] for i in self._index())


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
