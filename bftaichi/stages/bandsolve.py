"""Steps 3-6 on one band (DESIGN.md section 3): observe, prior, MAP, variance and the local
misfit, as :class:`bftaichi.Reconstructor` runs them on the whole band and
:mod:`.chunks` on each chunk's."""

from __future__ import annotations

import time

import numpy as np

from .misfit import local_misfit
from .observe import FramePicks, estimate_extra_noise, free_space_rows, make_observer, observe
from .prior import add_prior
from .sharednoise import shared_noise_factor
from .solve import prior_bias, solve_map
from .variance import estimate_variance

__all__ = ["Lap", "fit_noise", "solve_band"]


def fit_noise(cfg, band, frames) -> dict:
    """The frames' extra noise (``observation.fit_noise``) seen on ``band``."""
    o = cfg.observation
    if not o.fit_noise:
        return {"sigma_extra_m": 0.0, "sigma_corr_m": 0.0}
    return estimate_extra_noise(frames, band, o, cfg.tsdf.voxel_size_m,
                                cfg.tsdf.bootstrap_trunc_m,
                                (cfg.scene.depth_min_m, cfg.scene.depth_max_m))


def solve_band(cfg, band, x0, frames, variance: bool, frame_iter, lap,
               noise: dict | None = None) -> dict:
    """Steps 3-6 on ``band`` (PCG start ``x0``) with the frames' ``noise`` (default: fitted
    on ``band``): the Posterior's fields mean, var, cov, noise, solver, variance and
    observations. ``lap`` (a :class:`Lap`) times the sub-stages."""
    vs, tau, o = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m, cfg.observation
    if noise is None:
        noise = fit_noise(cfg, band, frames)
    lap("noise")
    # observation.shared_in_map: the correlated part shared by the L frames of a run (at most
    # every frame: one error shared by all of them)
    L = (min(max(float(noise.get("frames_sharing_noise", 1.0)), 1.0), max(len(frames), 1))
         if o.shared_in_map else 1.0)
    observer = make_observer(band, o, vs, tau, noise["sigma_extra_m"],            # step 3
                             noise["sigma_corr_m"] * L ** 0.5)
    free_space = None
    if cfg.prior.free > 0 and cfg.prior.carve > 0:
        from kernels.carve import FreeSpaceCounter

        todo = free_space_rows(band, tau)
        free_space = FreeSpaceCounter(band.ijk[todo], vs, cfg.tsdf.bootstrap_trunc_m)
    S, h_data, counts = observe(observer, frame_iter(frames, "observe") if frame_iter
                                else frames, o.stride, free_space)
    carved = None
    if free_space is not None:  # seen as free space by at least `carve` of its frames, and 2
        n_carved = free_space.carved()
        carved = np.zeros(len(band), bool)
        carved[todo] = (n_carved >= 2) & (n_carved >= cfg.prior.carve * free_space.observing())
    observer.release()  # the misfit pass below needs only its lookups
    bias_on = variance and cfg.solver.prior_bias
    share = variance and (cfg.solver.variance != "posterior" or bias_on)  # the data's share
    W = (S.sum(axis=1, dtype=np.float64).astype(np.float32)
         if share and cfg.solver.variance == "blend-sampled" else None)  # its row sums
    lap("observe")
    system = add_prior(S, h_data, band, cfg.prior, cfg.band.stencil, vs)          # step 4
    data = (W, system.data_diagonal) if share else None
    lap("prior")
    mean, map_stats = solve_map(system, x0, cfg.solver, band, trunc_m=tau,        # step 5
                                bootstrap_trunc_m=cfg.tsdf.bootstrap_trunc_m,
                                voxel_size_m=vs, free=cfg.prior.free,
                                prior=cfg.prior, carved=carved)
    lap("map")
    bias = None
    if bias_on:  # the MAP's bias under its prior, estimated at the mean (step 6)
        bias = prior_bias(system, band, cfg.prior, cfg.band.stencil, vs, mean, cfg.solver)
        lap("bias")
    system.compact = None  # the MAP's layout (prior_bias's): not the probes'
    kappa = shared_noise_factor(band.weight, noise)  # frames in a row share their noise
    var, cov, var_stats = estimate_variance(system, cfg.solver, band.ijk,          # step 6
                                            probes=variance, data=data, bias=bias,
                                            kappa=kappa)
    lap("variance")
    if o.local_noise:  # the model error b^2 (fully correlated between neighbours) added
        picked = FramePicks(frames, o.misfit_frames)
        b2, misfit = local_misfit(observer, frame_iter(picked, "misfit") if frame_iter
                                  else picked, mean, var, band.nbr, o.stride)
        misfit["frames"] = len(picked)
        var = var + b2
        if variance:
            from .variance import _face_neighbours, _faces

            b, faces = np.sqrt(b2), _faces(band.nbr)
            cov = np.where(faces >= 0, cov + b[:, None] * _face_neighbours(faces, b), 0)
        var_stats = dict(var_stats, local_noise=misfit)
        lap("misfit")
    return {"mean": mean, "var": np.asarray(var, np.float32),
            "cov": cov if variance else None,
            "sigma_extra_m": float(noise["sigma_extra_m"]),
            "sigma_corr_m": float(noise["sigma_corr_m"]), "solver": map_stats,
            "variance": _plain(var_stats),
            "observations": _plain(dict(counts, noise_fit=noise))}



_COLLECT_MIN = 100_000  # band voxels from which each solve sub-stage frees compile arguments


class Lap:
    """Seconds of each sub-stage of :meth:`Reconstructor.solve`, in order. With ``collect``
    (bands of at least :data:`_COLLECT_MIN` voxels) each sub-stage ends with
    :func:`kernels.stencil.free_compile_arguments`, so its large temporaries (layout tables,
    probe vectors) do not stay resident into the next (~90 MB at the probes on redkitchen at
    2 cm); below that the ~0.06 s it costs is worth more (a scan solves every step)."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.t0 = time.perf_counter()
        self.collect = True

    def __call__(self, name: str) -> None:
        if self.collect:
            from kernels.stencil import free_compile_arguments

            free_compile_arguments()
        t1 = time.perf_counter()
        self.seconds[name] = round(self.seconds.get(name, 0.0) + t1 - self.t0, 4)  # chunks add
        self.t0 = t1


def _plain(d: dict) -> dict:
    """JSON-ready copy: numpy scalars to Python, arrays to lists."""
    return {k: v.tolist() if isinstance(v, np.ndarray) else v.item()
            if isinstance(v, np.generic) else v for k, v in d.items()}
