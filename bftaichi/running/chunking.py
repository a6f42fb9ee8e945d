"""A chunk size that fits the memory budget (issue 20; ``run.chunk_m``).

When the estimate of a whole-band solve (:func:`.resources.estimate_memory`) exceeds the
budget, :func:`.resources.check_memory` asks :func:`choose_chunk` for the largest chunk side
whose run fits, and the run goes on in chunks of that side, saying so
(:class:`ChunkingWarning`, ``report.json``'s ``memory.estimate.chunk_m_chosen``), instead of
refusing. What chunking cannot shrink is what the whole scene holds anyway: the TSDF, its
export and mesh, the whole band and its stitched mean, variance and covariance, and the
posterior mesh; when those alone exceed the budget the run is refused as before, naming a
voxel size that fits.

The chunk's band is estimated from the scene sample: the share of the surface cells that the
densest chunk holds, grown by the halo (a surface's band grows as the square of the box's
side), times the whole band.
"""

from __future__ import annotations

import numpy as np

from ..errors import BftaichiWarning

__all__ = ["ChunkingWarning", "chunk_share", "choose_chunk"]

BLOCK = 8


class ChunkingWarning(BftaichiWarning):
    """The whole-band solve would not fit the memory budget: the run solves in chunks."""


def chunk_share(sample, voxel_size_m: float, side: int, halo: int) -> float:
    """Share (0 to 1) of the whole band that the densest chunk's band (core of ``side``
    voxels plus ``halo``) holds, from ``sample`` (a :class:`.resources.SceneSample`): its
    surface cells binned by chunk, the largest count over the total, times
    ``((side + 2 (halo + 1)) / side)^2``."""
    cell_ijk, cell_m = sample.surface_cells(voxel_size_m)
    if not len(cell_ijk):
        return 1.0
    chunk = np.floor((cell_ijk + 0.5) * cell_m / (side * voxel_size_m)).astype(np.int64)
    _, counts = np.unique(chunk, axis=0, return_counts=True)
    grow = ((side + 2 * (halo + 1)) / side) ** 2
    return float(min(1.0, counts.max() / len(cell_ijk) * grow))


def chunk_sides(sample, voxel_size_m: float) -> list[int]:
    """Candidate chunk sides, voxels (whole blocks), largest first: from the scene's largest
    extent down by factors of about 1.25, to one block."""
    top = max(1, int(np.ceil(max(sample.extent_m) / (BLOCK * voxel_size_m))))
    blocks, b = [], float(top)
    while b >= 1:
        blocks.append(int(round(b)))
        b /= 1.25
    return [BLOCK * k for k in sorted(set(blocks + [1]), reverse=True)]


def choose_chunk(cfg, sample, budget: int, model) -> tuple[float, dict] | None:
    """``(chunk_m, estimate)``: the largest chunk side whose estimate (``model(side, halo)``,
    the resources model of a chunked run) fits ``budget`` bytes; None if none does."""
    v = cfg.tsdf.voxel_size_m
    for side in chunk_sides(sample, v):
        est = model(side, cfg.run.chunk_halo)
        if est["peak_bytes"] <= budget:
            return round(side * v, 9), est
    return None
