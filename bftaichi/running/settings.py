"""``[run]``: how a run executes (the section :class:`bftaichi.config.Config` holds as ``run``)."""

from __future__ import annotations

from dataclasses import dataclass

from ..checks import MAX_SEED, check_choice, check_range

__all__ = ["RunConfig"]


@dataclass
class RunConfig:
    """``[run]``: how the run executes."""

    arch: str = "cpu"
    """Taichi backend: ``cpu`` (default; the product is CPU-first), ``cuda``, ``vulkan``, ``metal``."""

    seed: int = 0
    """Master seed of the run's random choices (synthetic noise has its own ``synthetic.seed``)."""

    stages: str = "full"
    """``full`` (TSDF bootstrap + probabilistic posterior: tsdf_mesh.ply and mesh.ply with sigma)
    or ``tsdf_only`` (the bootstrap alone, e.g. as a fast baseline)."""

    strict: bool = False
    """Refuse (exit code 2) input failing a check of :mod:`bftaichi.plausibility` (else a warning)
    and a MAP solve that did not converge (else ``report.json`` flags ``map_not_converged``)."""

    plots: bool = True
    """Write diagnostic PNGs into ``plots/`` at the end of a run (``bftaichi.running.plots``:
    precision / recall and F-score against threshold, sigma histogram, calibration, PCG
    residual; those without their inputs, e.g. without ground truth, are skipped)."""

    preview: bool = True
    """Write ``preview.html`` (a self-contained meshcat page of the result, ``bftaichi.running.viz``)
    at the end of a run."""

    keep_state: bool = False
    """Also write ``fusion_state.npz`` (the TSDF's integer sums, 24 bytes an observed voxel, and
    each frame's name and pose), so ``bftaichi update`` can move frames without re-fusing."""

    memory_fraction: float = 0.8
    """Peak memory a run may take, as a fraction (0 to 1) of the available RAM
    (:mod:`bftaichi.running.resources`: a run whose estimate exceeds it solves the posterior in
    the largest chunks that fit, saying so (``chunk_m``), or, when no chunk size fits, stops
    before allocating, naming a voxel size that fits). 0.8 leaves a fifth to the rest of the
    machine. Ignored when ``memory_budget_gib`` is set."""

    memory_budget_gib: float = 0.0
    """Peak memory a run may take, GiB, whatever is available (0 = use ``memory_fraction``)."""

    chunk_m: float = 0.0
    """Solve the posterior in spatial chunks: block-aligned cubes of about this side, metres
    (0 = one solve for the whole band). Each chunk's band (its core plus ``chunk_halo`` voxels
    around it) is solved on its own with the observations that fall in it, and each voxel takes
    the values of the chunk whose core holds it, so a scene larger than memory needs memory for
    one chunk's solve at a time (:mod:`bftaichi.stages.chunks`); under ``bftaichi batch`` the
    chunks are Ray tasks. Left at 0, a run over its memory budget chooses a size itself."""

    chunk_halo: int = 8
    """Voxels of band around each chunk's core that its solve includes and discards, so that
    the core does not feel the chunk's edge."""

    def check(self) -> None:
        check_choice("run.arch", self.arch, ("cpu", "cuda", "vulkan", "metal", "gpu"))
        check_choice("run.stages", self.stages, ("full", "tsdf_only"))
        check_range("run.memory_fraction", self.memory_fraction, 0.0, 1.0, lo_open=True)
        check_range("run.memory_budget_gib", self.memory_budget_gib, 0.0, 1e6)
        check_range("run.seed", self.seed, 0, MAX_SEED)
        check_range("run.chunk_m", self.chunk_m, 0.0, 1e4)
        check_range("run.chunk_halo", self.chunk_halo, 1, 64)
