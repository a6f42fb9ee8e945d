"""The probabilistic stage (DESIGN.md section 3, steps 2-7): band -> observations -> GMRF posterior
-> PCG MAP -> probe variance -> mesh with per-vertex sigma.

All heavy loops are Taichi kernels in ``kernels/`` (band, observe, prior, pcg); this module
validates, wires them together and packages the result as a :class:`Posterior`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import trimesh

from .config import Config
from .errors import NoSurfaceError

__all__ = ["Posterior", "solve_posterior"]


@dataclass
class Posterior:
    """The Gaussian posterior of the SDF over the narrow band.

    Attributes:
        ijk: (N, 3) int32 band voxel indices (centre ``(ijk + 0.5) * voxel_size``), sorted.
        voxel_size: metres.
        mean: (N,) float32 MAP signed distance, metres (positive in free space).
        var: (N,) float32 estimated marginal variance ``diag(Q^-1)``, metres^2.
        tsdf: (N,) float32 bootstrap TSDF value, metres; weight: (N,) float32 bootstrap weight.
        core: (N,) bool, voxel in the undilated band ``|tsdf| < alpha * tau``.
        solver: MAP PCG stats (converged, iterations, relative_residual).
        variance: probe stats (probes, method, iterations, not_converged).
        observations: counts of the observation pass.
        seconds: wall time of each sub-stage (band, observe, prior, map, variance).
        precision: ``(S, nbr, far)`` of the solved posterior (:mod:`kernels.pcg` stencil of Q),
            kept in memory for planning and tests (not saved); None for a loaded posterior.
    """

    ijk: np.ndarray
    voxel_size: float
    mean: np.ndarray
    var: np.ndarray
    tsdf: np.ndarray
    weight: np.ndarray
    core: np.ndarray
    solver: dict = field(default_factory=dict)
    variance: dict = field(default_factory=dict)
    observations: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    precision: tuple | None = field(default=None, repr=False)

    @classmethod
    def load(cls, path) -> "Posterior":
        """The posterior saved as ``band.npz`` by a run (``mean`` and ``var`` must be there:
        a ``run.stages = "tsdf_only"`` run has no posterior). Raises DataError naming the file."""
        from .errors import DataError

        try:
            with np.load(path) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise DataError(f"{path}: cannot read the band ({e})") from None
        missing = [k for k in ("ijk", "voxel_size", "mean", "var", "tsdf", "weight")
                   if k not in data]
        if missing:
            hint = " (a run.stages = 'tsdf_only' run has no posterior)" if "mean" in missing else ""
            raise DataError(f"{path}: missing arrays {', '.join(missing)}{hint}")
        n = len(data["ijk"])
        if data["ijk"].shape != (n, 3) or any(data[k].shape != (n,) for k in
                                              ("mean", "var", "tsdf", "weight")):
            raise DataError(f"{path}: arrays ijk (N, 3) and mean/var/tsdf/weight (N,) disagree")
        return cls(ijk=data["ijk"].astype(np.int32), voxel_size=float(data["voxel_size"]),
                   mean=data["mean"].astype(np.float32), var=data["var"].astype(np.float32),
                   tsdf=data["tsdf"].astype(np.float32),
                   weight=data["weight"].astype(np.float32), core=data["weight"] > 0)

    def save(self, out_dir) -> "Path":
        """Write ``mesh.ply`` (:meth:`extract_mesh`, vertex ``sigma``) and ``band.npz`` (``ijk,
        voxel_size, mean, var, tsdf, weight``) into ``out_dir`` (DESIGN.md section 4),
        atomically; return the folder. :meth:`load` reads the band back."""
        from .io import ensure_out_dir, write_mesh_ply, write_npz

        out = ensure_out_dir(out_dir)
        mesh = self.extract_mesh()
        write_mesh_ply(out / "mesh.ply", mesh.vertices, mesh.faces,
                       vertex_attrs={"sigma": mesh.vertex_attributes["sigma"]})
        write_npz(out / "band.npz", ijk=self.ijk, voxel_size=np.float32(self.voxel_size),
                  mean=self.mean, var=self.var, tsdf=self.tsdf, weight=self.weight)
        return out

    @property
    def sigma(self) -> np.ndarray:
        """(N,) float32 posterior standard deviation, metres."""
        return np.sqrt(np.maximum(self.var, 0)).astype(np.float32)

    def extract_mesh(self) -> trimesh.Trimesh:
        """Marching cubes at ``mean = 0`` over cells whose 8 corners are band voxels observed by
        the bootstrap (weight > 0), with vertex attribute ``sigma`` (metres, trilinear from the
        voxel variances).

        Why observed corners only: in the one-voxel dilation around the band, nothing but the
        prior sets the mean, and the membrane prior flattens it toward the anchors and 0, which
        makes zero crossings where no surface was seen (measured on the default scene: 12 % of
        vertices more than 1 cm from the truth, 92 % of those in cells with an unobserved
        corner)."""
        from .meshing import extract_mesh, sample_field

        inside = np.ones(len(self.ijk), bool)
        vertices, faces = extract_mesh(self.ijk, self.mean, self.weight > 0, self.voxel_size)
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        if len(vertices):
            var = sample_field(self.ijk, self.var, inside, self.voxel_size, vertices)
            mesh.vertex_attributes["sigma"] = np.sqrt(np.maximum(np.nan_to_num(var), 0)).astype(
                np.float32)
        else:
            mesh.vertex_attributes["sigma"] = np.zeros(0, np.float32)
        return mesh


def solve_posterior(frames, voxels: dict, cfg: Config, frame_iter=None, *, warm_start=None,
                    variance: bool = True) -> Posterior:
    """Build the band from the bootstrap ``voxels`` (:meth:`TSDFVolume.export`), fuse the
    observations of ``frames``, solve the MAP and estimate the variance.

    ``frame_iter(frames, desc)`` yields the frames (the pipeline passes a prefetching iterator
    with a progress bar); default: plain iteration. ``warm_start``: an earlier Posterior whose
    mean starts PCG at the voxels both bands share (the TSDF elsewhere), as when frames are
    added one at a time. ``variance=False`` skips the probes (``var`` is then the conditional
    variance ``1/Q_ii``, a lower bound, and ``variance`` stats say so).
    """
    from kernels.band import build_band
    from kernels.layout import CENTRE
    from kernels.observe import Observer
    from kernels.pcg import pcg
    from kernels.probes import probe_variance
    from kernels.prior import add_curvature_prior, add_prior

    seconds = {}
    t0 = time.perf_counter()

    def lap(name):
        nonlocal t0
        t1 = time.perf_counter()
        seconds[name] = round(t1 - t0, 4)
        t0 = t1

    vs = cfg.tsdf.voxel_size_m
    band = build_band(voxels["ijk"], voxels["tsdf"], voxels["weight"], cfg.tsdf.bootstrap_trunc_m)
    n = len(band["ijk"])
    if n == 0:
        raise NoSurfaceError("the narrow band is empty: no observed voxel has |tsdf| below the "
                             "bootstrap truncation, so there is no surface to refine")
    lap("band")
    o = cfg.observation
    noise = {"sigma_extra_m": 0.0}
    if o.fit_noise:
        noise = estimate_extra_noise(frames, band, cfg)
    sigma_model = float(np.hypot(o.sigma_model_m, noise["sigma_extra_m"]))
    lap("noise")
    observer = Observer(band["block_keys"], band["block_table"], n, vs, cfg.tsdf.trunc_m,
                        spacing_m=o.spacing_voxels * vs, depth_a_m=o.depth_a_m, depth_b=o.depth_b,
                        depth_z0_m=o.depth_z0_m, cos_min=o.cos_min, sigma_pose_m=o.sigma_pose_m,
                        sigma_model_m=sigma_model, count_once=o.count_once,
                        front_m=o.front * cfg.tsdf.trunc_m,
                        reference=np.where(band["weight"] > 0, band["tsdf"],
                                           np.float32(np.nan)),
                        gate_m=o.gate * cfg.tsdf.trunc_m)
    for frame in (frame_iter(frames, "observe") if frame_iter else frames):
        observer.integrate(frame.depth_m, frame.K, frame.T_W_C, stride=o.stride)
    S, h_data, obs_stats = observer.finalize()
    obs_stats["noise_fit"] = noise
    lap("observe")

    # Prior strengths are per voxel^2 in the config (PriorConfig docstring).
    p = cfg.prior
    b0 = np.zeros(n, np.float32)
    add_prior(S, b0, band["nbr"], band["tsdf"], band["weight"], lam=p.lam / vs ** 2,
              lam_b=p.lam_b / vs ** 2, eps=p.eps / vs ** 2, stencil=cfg.band.stencil,
              anchors=p.anchors)
    if p.outer > 0:
        # The outer band (observed voxels with |tsdf| beyond tau): no observation sample
        # reaches them (samples lie within +-tau of the measured surface), so only the prior
        # would set them, and between occluding edges it can bend them through zero (false
        # surface in space the TSDF saw as free). Anchor them to the bootstrap.
        outer = (band["weight"] > 0) & (np.abs(band["tsdf"]) > cfg.tsdf.trunc_m)
        S[outer, CENTRE] += np.float32(p.outer / vs ** 2)
        b0[outer] += np.float32(p.outer / vs ** 2) * band["tsdf"][outer]
    far = None  # Q's entries at offsets +-2 (curvature prior only)
    if p.curvature > 0:
        far = add_curvature_prior(S, band["nbr"], lam2=p.curvature / vs ** 2)
    h = (h_data.astype(np.float64) + b0).astype(np.float32)
    lap("prior")

    s = cfg.solver
    x0 = band["x0"]
    if warm_start is not None and len(warm_start.ijk):
        x0 = _carry_over(warm_start, band["ijk"], x0)
    mean, info = pcg(S, band["nbr"], h, x0, tol=s.tol, maxiter=s.maxiter, far=far)
    free_stats = {"passes": 0, "anchored": 0, "free_voxels": 0}
    if p.free > 0:
        mean, info, free_stats = _free_space(S, band, h, mean, info, cfg, far)
    lap("map")
    floor = (1.0 / S[:, CENTRE].astype(np.float64)).astype(np.float32)
    if variance:
        var, vinfo = probe_variance(S, band["nbr"], n_probes=s.probes, seed=s.seed,
                                    method=s.probe_method, tol=s.probe_tol, maxiter=s.maxiter,
                                    ijk=band["ijk"], far=far)
        # The probe estimate can dip below the conditional variance 1/Q_ii (or below 0) where
        # few probes average out; the marginal variance is never smaller than 1/Q_ii, so floor
        # it there.
        vinfo = dict(vinfo, n_floored=int(np.count_nonzero(var < floor)))
        var = np.maximum(var, floor)
    else:
        var, vinfo = floor, {"n_probes": 0, "method": "conditional (1/Q_ii, no probes)"}
    lap("variance")
    solver = {k: info[k] for k in ("converged", "iterations", "relative_residual")}
    solver["free_space"] = free_stats
    if "reason" in info:
        solver["reason"] = info["reason"]
    solver["residual_history"] = [float(r) for r in info.get("residual_history", [])]
    return Posterior(ijk=band["ijk"], voxel_size=vs, mean=np.asarray(mean, np.float32),
                     var=np.asarray(var, np.float32), tsdf=band["tsdf"], weight=band["weight"],
                     core=band["core"], solver=solver, variance=_plain(vinfo),
                     observations=_plain(obs_stats), seconds=seconds,
                     precision=(S, band["nbr"], far))


def estimate_extra_noise(frames, band: dict, cfg: Config, *, n_frames: int = 16,
                         stride: int = 4) -> dict:
    """Per-pixel depth noise the sensor model does not explain, fitted to the frames themselves.

    Recorded trajectories carry pose and calibration errors that no axial noise model holds
    (on 7-Scenes the held-out depth residual is ~2x the Kinect model's sigma). The bootstrap TSDF
    is rendered (:func:`kernels.raycast.raycast_depth`, observed band cells) at up to
    ``n_frames`` frames spread over the sequence, every ``stride``-th pixel; the residuals
    ``r = z_tsdf - D`` with ``|r| < alpha tau`` (gross ones, e.g. at occlusion edges, are no
    noise) are modelled as ``N(0, sigma_D(D)^2 + e^2)``, ``sigma_D = a + b (D - z0)^2``, and
    ``e >= 0`` solves ``median(|r| / sqrt(sigma_D^2 + e^2)) = 0.6745`` (the median of a
    standard normal's ``|x|``; 0 when the model alone already reaches it). Robust to the
    outliers and deterministic. The TSDF holds the frame itself (in-sample), so ``e`` is
    biased low by about ``1/n`` of the variance for a point seen in n frames.

    Returns ``{"sigma_extra_m": e, "pixels": n, "frames": k, "median_normalised_model": m0}``
    (m0: the statistic with ``e = 0``; 0.6745 is calibrated)."""
    from kernels.raycast import raycast_depth

    o, vs = cfg.observation, cfg.tsdf.voxel_size_m
    n = len(frames)
    picks = np.unique(np.linspace(0, n - 1, min(n_frames, n)).round().astype(int)) if n else []
    observed = (band["weight"] > 0).astype(np.uint8)
    r_all, s_all = [], []
    for i in picks:
        f = frames[int(i)]
        h, w = f.depth_m.shape
        z = raycast_depth(band["block_keys"], band["block_table"], band["tsdf"], observed, vs,
                          f.K, f.T_W_C, w, h, cfg.scene.depth_min_m, cfg.scene.depth_max_m,
                          stride=stride)
        D = np.asarray(f.depth_m, np.float64)
        both = (z > 0) & (D > 0)
        r = z[both] - D[both]
        keep = np.abs(r) < cfg.tsdf.bootstrap_trunc_m
        r_all.append(np.abs(r[keep]))
        s_all.append(o.axial_sigma_m(D[both][keep]))
    r = np.concatenate(r_all) if r_all else np.zeros(0)
    s = np.concatenate(s_all) if s_all else np.zeros(0)
    target = 0.6744897501960817  # median of |N(0, 1)|
    if len(r) < 100:
        return {"sigma_extra_m": 0.0, "pixels": int(len(r)), "frames": int(len(picks)),
                "median_normalised_model": None}

    def stat(e):
        return float(np.median(r / np.sqrt(s * s + e * e)))

    m0 = stat(0.0)
    e = 0.0
    if m0 > target:  # bisection: stat decreases with e
        lo, hi = 0.0, max(float(np.median(r)) / target, 1e-6)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if stat(mid) > target else (lo, mid)
        e = hi
    return {"sigma_extra_m": e, "pixels": int(len(r)), "frames": int(len(picks)),
            "median_normalised_model": m0}


def fitted_extra_noise(observations: dict | None) -> float:
    """The extra noise ``e`` (metres) a run fitted to its frames, from its observation stats
    (``Posterior.observations``, report.json ``solver.observations``); 0 without a fit."""
    return float(((observations or {}).get("noise_fit") or {}).get("sigma_extra_m") or 0.0)


def _free_space(S, band, h, mean, info, cfg: Config, far, passes: int = 4):
    """The free-space inequality of ``prior.free`` by an active set (PriorConfig.free): anchor
    the violators ``tsdf > tau``, ``mean < voxel / 2`` to their TSDF value in ``S`` and ``h``
    (in place) and re-solve, up to ``passes`` times. Returns the final ``(mean, info, stats)``;
    ``info`` is the last solve's and its iterations are summed over the solves."""
    from kernels.layout import CENTRE
    from kernels.pcg import pcg

    vs, s = cfg.tsdf.voxel_size_m, cfg.solver
    k = np.float32(cfg.prior.free / vs ** 2)
    free = (band["weight"] > 0) & (band["tsdf"] > cfg.tsdf.trunc_m)
    active = np.zeros(len(free), bool)
    iterations = info["iterations"]
    n_pass = 0
    for n_pass in range(1, passes + 1):
        viol = free & ~active & (mean < 0.5 * vs)
        if not viol.any():
            n_pass -= 1
            break
        active |= viol
        S[viol, CENTRE] += k
        h[viol] += k * band["tsdf"][viol]
        mean, info = pcg(S, band["nbr"], h, mean, tol=s.tol, maxiter=s.maxiter, far=far)
        iterations += info["iterations"]
    info = dict(info, iterations=iterations)
    return mean, info, {"passes": n_pass, "anchored": int(active.sum()),
                        "free_voxels": int(free.sum())}


def _carry_over(prev: Posterior, ijk: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """``x0`` with the voxels of ``ijk`` that ``prev`` also holds set to ``prev.mean``."""
    from kernels.layout import block_key_np

    def key(a):  # one int64 per voxel, ascending in the bands' lexicographic order
        return block_key_np(np.asarray(a, np.int64))

    k_prev, k_new = key(prev.ijk), key(ijk)
    pos = np.clip(np.searchsorted(k_prev, k_new), 0, len(k_prev) - 1)
    same = k_prev[pos] == k_new
    out = np.array(x0, np.float32, copy=True)
    out[same] = prev.mean[pos[same]]
    return out


def _plain(d: dict) -> dict:
    """JSON-ready copy: numpy scalars to Python, arrays to lists."""
    out = {}
    for k, v in d.items():
        if isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out
