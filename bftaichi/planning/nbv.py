"""Next-best-view planning (DESIGN.md section 3.8): rank candidate camera poses by the posterior
variance their depth image would remove.

For a candidate view ``v`` (pose ``T_W_C``, the run's intrinsics):

1. **Predicted depth** (:func:`kernels.raycast.raycast_depth`): the first ``mu = 0`` crossing of
   the posterior mean along each (strided) pixel ray, through observed band cells only. The
   ray stops at the first surface, so what another object hides is not counted (occlusion).
2. **Hypothetical observations**: the predicted depth goes through the same observation model
   as real frames (:class:`kernels.observe.Observer`: normals, samples within ``+-tau``,
   trilinear rows, the configured depth noise at that depth and angle, each pixel counted once
   per voxel). Their information on voxel ``i`` is ``d_i = (A_v^T W_v A_v)_ii``.
3. **Known surface**: ``U_known = sum_{i in Omega_eps} (s_i - s'_i)`` over the observed band
   voxels with ``|mu_i| <= eps``, with the *local update* ``s'_i = s_i / (1 + s_i d_i)``: the
   exact posterior variance of voxel i if the view's information on it were the only change
   (a rank-one update of Q along ``e_i``), ``s_i`` the posterior variance capped at step 4's
   ``s0``: a seen voxel is no less certain than an unseen one (the prior's bias, which the
   variance carries as an offset, reached centimetres on a few voxels of a two-view scan,
   and without the cap those few ranked the views; docs/measurements.md). It ignores the
   correlations between voxels (what one voxel learns, its correlated neighbours partly knew;
   a view's information couples
   neighbouring voxels), so it is off the exact reduction, by 0.52-2.05x on the small problem
   of tests/test_nbv.py, but ranks the candidates like it: checked against
   ``diag((Q + A_v^T W_v A_v)^-1)`` there (Spearman of the two rankings over 16 candidates
   >= 0.85).
4. **Unknown space**: a ray that leaves the space some frame has seen (:class:`CoverageGrid`,
   a coarse grid over the region of interest) before the predicted surface, or with no
   surface predicted, enters unseen space at its *frontier cell*; what it would observe there
   is new surface (or new free space). ``U_unknown = rho * g0 * n_frontier``: ``n_frontier``
   the distinct frontier cells of the view's rays, each assumed to hold surface as densely as
   the seen surface cells do, ``rho = |Omega_eps| / (cells holding an Omega_eps voxel)``, each
   such voxel scored at the prior variance: ``g0 = s0 - s0 / (1 + s0 w0)`` the reduction a
   voxel at the prior variance ``s0`` gets from one view: ``s0 =
   (alpha tau)^2 / 3``, the variance of an SDF value known only to lie within the bootstrap
   truncation (uniform on ``[-alpha tau, alpha tau]``; the band's unobserved dilation voxels
   are no guide, the boundary anchors pin them), ``w0`` the information of the pixels a voxel
   face collects at the candidate's distance (noise model at that depth, head-on). Counting
   the frontier (an area) rather than every unseen cell a ray crosses (a volume: the
   ``coverage`` policy of ``bftaichi scan``) keeps the inside of objects, which no view sees,
   from counting as surface.

``U(v) = U_known + U_unknown``, metres^2. Without step 4 a planner can never improve
completeness: unseen surface has no voxels in the band to score.

Coordinates: candidate poses, targets, the region of interest and the coverage grid are in
world coordinates (the coverage kernels ray-march in float64); only the band's kernels (steps
1 and 2) get a candidate's pose moved into the posterior's local frame (``post.origin``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from kernels.layout import column_max, column_min

from ..config import Config
from ..errors import ConfigError, DataError
from ..geometry import check_pose, look_at, points_in_world, pose_in_local

__all__ = ["sphere_candidates", "ring_candidates", "load_poses", "make_candidates",
           "candidates_around", "rank", "CoverageGrid", "region_of_interest", "Planner", "plan",
           "read_ranking"]


# -- candidates --------------------------------------------------------------------------------

def sphere_candidates(target, radius_m: float, n: int, min_elevation_deg: float = -90.0,
                      max_elevation_deg: float = 90.0) -> np.ndarray:
    """``n`` poses ``T_W_C`` (n, 4, 4) on a Fibonacci lattice of the sphere of ``radius_m``
    around ``target`` between the two elevations (even in area), each looking at ``target``
    with up = +z. Deterministic."""
    target = np.asarray(target, np.float64).reshape(3)
    k = np.arange(n, dtype=np.float64)
    z_lo = math.sin(math.radians(min_elevation_deg))
    z_hi = math.sin(math.radians(max_elevation_deg))
    z = z_hi - (k + 0.5) / n * (z_hi - z_lo)
    az = k * np.pi * (3.0 - math.sqrt(5.0))  # golden angle
    rho = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    eyes = target + radius_m * np.stack([rho * np.cos(az), rho * np.sin(az), z], 1)
    return np.stack([look_at(e, target) for e in eyes])


def ring_candidates(target, radius_m: float, n: int, height_m: float = 0.0,
                    phase_rad: float = 0.0) -> np.ndarray:
    """``n`` poses evenly spaced on a horizontal circle of ``radius_m`` at ``height_m`` above
    ``target`` (the first at azimuth ``phase_rad`` from +x), looking at ``target``."""
    target = np.asarray(target, np.float64).reshape(3)
    az = phase_rad + 2.0 * np.pi * np.arange(n) / n
    eyes = target + np.stack([radius_m * np.cos(az), radius_m * np.sin(az),
                              np.full(n, float(height_m))], 1)
    return np.stack([look_at(e, target) for e in eyes])


def load_poses(path) -> np.ndarray:
    """Candidate poses ``T_W_C`` (n, 4, 4) from a text file with one row-major 4x4 matrix per
    line (16 numbers), or from a folder of ``*.txt`` files holding one 4x4 matrix each (sorted
    by name). Every pose is checked (finite, rigid, last row 0 0 0 1); errors name the file and
    line."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"nbv.poses_file: {path} does not exist")
    poses = []
    if path.is_dir():
        files = sorted(path.glob("*.txt"))
        if not files:
            raise DataError(f"nbv.poses_file: folder {path} holds no *.txt pose files")
        for f in files:
            try:
                T = np.loadtxt(f, dtype=np.float64).reshape(4, 4)
            except ValueError as e:
                raise DataError(f"{f}: not a 4x4 matrix ({e})") from None
            poses.append(check_pose(T, str(f)))
    else:
        lines = path.read_text().splitlines()
        for n, line in enumerate(lines, 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            try:
                values = [float(v) for v in line.replace(",", " ").split()]
            except ValueError:
                raise DataError(f"{path}:{n}: not a list of numbers") from None
            if len(values) != 16:
                raise DataError(f"{path}:{n}: expected 16 numbers (a row-major 4x4 T_W_C), "
                                f"got {len(values)}")
            poses.append(check_pose(np.array(values).reshape(4, 4), f"{path}:{n}"))
        if not poses:
            raise DataError(f"{path}: no poses")
    return np.stack(poses)


def make_candidates(cfg: Config, target, radius_m: float) -> np.ndarray:
    """The candidate poses of ``cfg.nbv`` around ``target`` at ``radius_m`` (n, 4, 4)."""
    c = cfg.nbv
    if c.candidates == "file":
        return load_poses(c.poses_file)
    if c.candidates == "ring":
        return ring_candidates(target, radius_m, c.n_candidates, c.height_m)
    if c.candidates == "rings":
        k = len(c.heights_m)
        sizes = [c.n_candidates // k + (r < c.n_candidates % k) for r in range(k)]
        return np.concatenate([ring_candidates(target, radius_m, n, float(h),
                                               phase_rad=np.pi / n if r % 2 else 0.0)
                               for r, (n, h) in enumerate(zip(sizes, c.heights_m))])
    lo = c.min_elevation_deg if c.candidates == "sphere" else max(c.min_elevation_deg, 10.0)
    return sphere_candidates(target, radius_m, c.n_candidates, lo, c.max_elevation_deg)


# -- seen / unknown space ----------------------------------------------------------------------

def region_of_interest(ijk: np.ndarray, voxel_size: float, scale: float, target=None,
                       origin=None) -> tuple:
    """``(lo, hi)`` (3,) metres, world frame: a cube of side ``scale`` times the longest side
    of the voxels' bounding box, centred on ``target`` (world; default: the box centre).
    ``ijk`` are in the local grid of ``origin`` (None: the world's)."""
    if len(ijk) == 0:
        raise DataError("the band is empty: no region of interest to plan views for")
    lo = column_min(ijk) * voxel_size
    hi = (column_max(ijk) + 1) * voxel_size
    if origin is not None:
        lo, hi = points_in_world(lo, origin), points_in_world(hi, origin)
    centre = 0.5 * (lo + hi) if target is None or len(target) == 0 else np.asarray(target,
                                                                                  np.float64)
    half = 0.5 * scale * float((hi - lo).max())
    return centre - half, centre + half


class CoverageGrid:
    """Which cells of the region of interest some frame has seen (a ray crossed them up to its
    surface, or the surface itself): :class:`kernels.coverage.CoverageGrid` over a cube of
    ``cells`` per side (never finer than ``voxel_size``)."""

    def __init__(self, lo, hi, cells: int, voxel_size: float, trunc_m: float,
                 miss_depth_m: float = 0.0):
        from kernels.coverage import CoverageGrid as _Grid

        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        cell = max(float((hi - lo).max()) / cells, voxel_size)
        self.grid = _Grid(lo, hi, cell)
        self.trunc_m = float(trunc_m)
        self.miss_depth_m = float(miss_depth_m)
        self.lo, self.hi, self.cell_m = lo, hi, cell

    def mark(self, depth_m, K, T_W_C, stride: int = 2) -> None:
        """Mark what one real frame saw: rays up to depth + tau; pixels without depth up to
        ``miss_depth_m`` (0: nothing)."""
        self.grid.mark(depth_m, K, T_W_C, self.trunc_m, stride=stride,
                       miss_depth_m=self.miss_depth_m)

    def count_unknown(self, depth_pred, K, T_W_C, stride: int, max_depth_m: float,
                      frontier: bool = False) -> int:
        """Distinct unseen cells the view's rays cross up to the predicted depth (or
        ``max_depth_m``); with ``frontier``, only each ray's first unseen cell."""
        return int(self.grid.count_unknown(depth_pred, K, T_W_C, stride=stride,
                                           max_depth_m=max_depth_m, frontier=frontier))

    def count_frontier(self, depth_pred, K, T_W_C, stride: int, max_depth_m: float,
                       not_frontier=None) -> int:
        """Distinct frontier cells (unseen, with a seen face neighbour) the view's rays cross
        up to the predicted depth (or ``max_depth_m``); ``not_frontier``: the grid's
        :meth:`kernels.coverage.CoverageGrid.not_frontier`, when scoring many views of one
        grid."""
        return int(self.grid.count_frontier(depth_pred, K, T_W_C, stride=stride,
                                            max_depth_m=max_depth_m,
                                            not_frontier=not_frontier))

    def average_entropy(self, depth_pred, K, T_W_C, stride: int, max_depth_m: float) -> float:
        """Isler et al. 2016's *average entropy* of the cells the view's rays cross up to the
        predicted depth (or ``max_depth_m``), every crossing counted:
        ``(n_u H(0.5) + n_s H(P_SEEN)) / (n_u + n_s)`` nats, ``H(p) = -p ln p - (1 - p)
        ln(1 - p)``, ``n_u`` / ``n_s`` the unseen / seen cells crossed; a seen cell has the
        occupancy probability of free space after one miss, clamped (``P_SEEN``), an unseen one
        0.5. 0 for a view whose rays cross no cell of the grid."""
        n_u, n_s = self.grid.tally(depth_pred, K, T_W_C, stride=stride, max_depth_m=max_depth_m)
        if n_u + n_s == 0:
            return 0.0
        return (n_u * _entropy(0.5) + n_s * _entropy(P_SEEN)) / (n_u + n_s)

    def cells_of(self, points) -> np.ndarray:
        """(n,) int64 flat cell index of world points (n, 3), clipped to the grid."""
        shape = np.array(self.grid.shape)
        c = np.clip(np.floor((np.asarray(points) - self.lo) / self.cell_m).astype(np.int64),
                    0, shape - 1)
        return np.ravel_multi_index(c.T, self.grid.shape)

    def seen_count(self) -> int:
        return int(self.grid.seen_count())


#: Occupancy probability of a seen cell for the entropy baseline: OctoMap's lower clamping
#: threshold (Hornung et al. 2013), what repeated misses leave of a free cell.
P_SEEN = 0.12


def _entropy(p: float) -> float:
    return float(-p * np.log(p) - (1.0 - p) * np.log(1.0 - p))


def coverage_grid(cfg: Config, lo, hi, voxel_size: float) -> CoverageGrid:
    """The coverage grid of ``cfg.nbv`` over the box ``lo, hi``."""
    return CoverageGrid(lo, hi, cfg.nbv.coverage_cells, voxel_size, cfg.tsdf.trunc_m,
                        cfg.scene.depth_max_m if cfg.nbv.miss_as_free else 0.0)


# -- the planner -------------------------------------------------------------------------------

class Planner:
    """Scores candidate views of a :class:`~bftaichi.posterior.Posterior` (module docstring).

    Args:
        post: the posterior (``mean``, ``var``, ``weight``, ``ijk``, ``voxel_size``,
            ``origin``).
        cfg: the run's configuration (observation model, ``tsdf.trunc_m``, ``nbv``).
        K: (3, 3) intrinsics and ``image_size`` (width, height) of the candidate camera.
        coverage: what the fused frames have seen; None scores known surface only.
        depth_range: ``(min, max)`` metres of the predicted depth.

    Poses given to its methods are world poses ``T_W_C``.
    """

    def __init__(self, post, cfg: Config, K, image_size, coverage: CoverageGrid | None = None,
                 depth_range: tuple | None = None):
        from ..stages.observe import make_observer

        self.post, self.cfg, self.coverage = post, cfg, coverage
        self.K = np.asarray(K, np.float64)
        self.width, self.height = (int(v) for v in image_size)
        vs = post.voxel_size
        # the solve's observation model, read back with the posterior (band.npz); a posterior
        # without it (an older band.npz) takes the config's
        o = self.observation = post.observation or cfg.observation
        tau = post.trunc_m or cfg.tsdf.trunc_m
        self.stride = cfg.nbv.stride or o.stride
        self.depth_range = depth_range or (cfg.scene.depth_min_m, cfg.scene.depth_max_m)
        self.observed = post.band.observed.astype(np.uint8)
        self._crossing = None  # kernels.raycast.crossing_blocks of the band, on first use
        # the noise fitted to the fused frames (ObservationConfig.fit_noise) holds for new ones
        self.sigma_model_m = float(np.hypot(o.sigma_model_m, post.sigma_extra_m))
        self.observer = make_observer(post.band, o, vs, tau, post.sigma_extra_m,
                                      post.sigma_corr_m)
        self.observer.release()  # information() needs only the lookups and the model
        eps = cfg.nbv.eps_voxels * vs
        self.omega = (post.weight > 0) & (np.abs(post.mean) <= eps)
        # prior variance of an unseen voxel: its SDF, clamped to the bootstrap truncation
        # (alpha tau), could be anywhere in [-alpha tau, alpha tau]: uniform, variance (.)^2 / 3
        self.s0 = (post.bootstrap_trunc_m or cfg.tsdf.bootstrap_trunc_m) ** 2 / 3.0
        # a seen voxel is no less certain than an unseen one: its variance is capped at s0
        # (the prior's bias, added to the variance as an offset, reaches centimetres on a
        # few voxels of a sparse scan, and those few then decided the ranking)
        self.s_omega = np.minimum(np.asarray(post.var, np.float64)[self.omega], self.s0)
        self.rho = 0.0  # Omega voxels per seen cell that holds any
        if coverage is not None and self.omega.any():
            centres = points_in_world((post.ijk[self.omega] + 0.5) * vs, post.origin)
            self.rho = float(self.omega.sum()) / len(np.unique(coverage.cells_of(centres)))

    def predict_depth(self, T_W_C, stride: int | None = None) -> np.ndarray:
        """(H, W) float32 predicted depth of a view (0 where no surface is predicted), at every
        ``stride``-th pixel (default: the planner's)."""
        from kernels.raycast import crossing_blocks, raycast_depth

        band = self.post.band
        T_L_C = pose_in_local(T_W_C, self.post.origin)
        if self._crossing is None:  # one band for every view: its crossing blocks once
            self._crossing = crossing_blocks(band.block_keys, band.block_table, self.post.mean,
                                             self.observed)
        return raycast_depth(band.block_keys, band.block_table, self.post.mean, self.observed,
                             self.post.voxel_size, self.K, T_L_C, self.width, self.height,
                             self.depth_range[0], self.depth_range[1],
                             stride=stride or self.stride, crossing=self._crossing)

    def information(self, depth, T_W_C, stride: int | None = None) -> np.ndarray:
        """(N,) float64 ``(A_v^T W_v A_v)_ii`` of the hypothetical frame ``depth`` (cast at
        ``stride``, default the planner's) at T_W_C, scaled to the real frames' stride."""
        stride = stride or self.stride
        scale = (stride / self.observation.stride) ** 2
        return self.observer.information(depth, self.K, pose_in_local(T_W_C, self.post.origin),
                                         stride=stride) * scale

    def _prior_gain(self, T_W_C) -> float:
        """``g0 = s0 - s0 / (1 + s0 w0)`` at the candidate's distance to the region's centre."""
        o = self.observation
        centre = 0.5 * (self.coverage.lo + self.coverage.hi)
        dist = float(np.linalg.norm(np.asarray(T_W_C)[:3, 3] - centre))
        sigma2 = o.axial_sigma_m(dist) ** 2 + o.sigma_pose_m ** 2 + self.sigma_model_m ** 2
        f = 0.5 * (self.K[0, 0] + self.K[1, 1])
        pixels = (self.post.voxel_size * f / (max(dist, 1e-6) * o.stride)) ** 2
        w0 = max(pixels, 1e-3) / sigma2
        return self.s0 - self.s0 / (1.0 + self.s0 * w0)

    def utility(self, T_W_C, stride: int | None = None) -> dict:
        """Score one view, its rays cast at every ``stride``-th pixel (default: the
        planner's): ``utility`` (metres^2) = ``known`` + ``unknown``, and ``frontier_cells``,
        ``hit_fraction`` (of the strided pixels that predict a surface), ``stride``."""
        T_W_C = check_pose(T_W_C, "candidate pose")
        stride = stride or self.stride
        depth = self.predict_depth(T_W_C, stride)
        d = self.information(depth, T_W_C, stride)[self.omega]
        s = self.s_omega
        known = float(np.sum(s * s * d / (1.0 + s * d)))  # sum (s - s / (1 + s d))
        cells, unknown = 0, 0.0
        if self.coverage is not None:
            cells = self.coverage.count_unknown(depth, self.K, T_W_C, stride,
                                                self.depth_range[1], frontier=True)
            unknown = self.rho * self._prior_gain(T_W_C) * cells
        n_px = len(range(0, self.height, stride)) * len(range(0, self.width, stride))
        return {"utility": known + unknown, "known": known, "unknown": unknown,
                "frontier_cells": cells, "hit_fraction": float(np.count_nonzero(depth)) / n_px,
                "stride": stride}

    def rank(self, poses, progress=None) -> list[dict]:
        """Score every pose (n, 4, 4); return dicts (``index``, ``rank`` 0 = best, ``pose``,
        the :meth:`utility` fields) sorted best first (ties keep the candidate order).

        With ``nbv.rerank = k > 0`` (and more than k poses) every pose is first scored at
        twice the planner's stride, a screen with four times fewer rays; the k best of the
        screen are scored again at the full stride and ranked first, by that score; the others
        follow in the screen's order with the screen's fields (``stride`` says which)."""
        poses = np.asarray(poses, np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
            raise ConfigError(f"candidate poses must be (n, 4, 4) with n >= 1, got {poses.shape}")
        k = self.cfg.nbv.rerank
        screen = 2 * self.stride if 0 < k < len(poses) else None
        it = progress(range(len(poses))) if progress else range(len(poses))
        scored = [dict(index=i, pose=poses[i].tolist(), **self.utility(poses[i], screen))
                  for i in it]
        order = sorted(range(len(scored)), key=lambda i: (-scored[i]["utility"], i))
        if screen is not None:
            top = order[:k]
            for i in top:
                scored[i].update(self.utility(poses[i]))
            order = sorted(top, key=lambda i: (-scored[i]["utility"], i)) + order[k:]
        return [dict(scored[i], rank=r) for r, i in enumerate(order)]


def plan(post, cfg: Config, frames, K, image_size, progress=None) -> dict:
    """Rank ``cfg.nbv``'s candidates for ``post`` after ``frames`` (an iterable of frames,
    used to mark the seen space). Returns the ``nbv.json`` content: ``candidates`` (ranked,
    best first), ``best``, and the planner's settings (target, radius, region of interest,
    ``s0``, ``rho``)."""
    target = cfg.nbv.target or None
    lo, hi = region_of_interest(post.ijk, post.voxel_size, cfg.nbv.roi_scale, target,
                                post.origin)
    centre = 0.5 * (lo + hi)
    radius = cfg.nbv.radius_m
    if radius <= 0:
        bbox_lo = column_min(post.ijk) * post.voxel_size
        bbox_hi = (column_max(post.ijk) + 1) * post.voxel_size
        radius = cfg.nbv.radius_scale * 0.5 * float(np.linalg.norm(bbox_hi - bbox_lo))
    poses = make_candidates(cfg, centre, radius)
    coverage = coverage_grid(cfg, lo, hi, post.voxel_size)
    for frame in frames:
        coverage.mark(frame.depth_m, frame.K, frame.T_W_C, stride=cfg.observation.stride)
    planner = Planner(post, cfg, K, image_size, coverage)
    ranked = planner.rank(poses, progress=progress)
    return {"candidates": ranked, "best": ranked[0],
            "settings": {"target": centre.tolist(), "radius_m": radius,
                         "roi": [lo.tolist(), hi.tolist()], "cell_m": coverage.cell_m,
                         "seen_cells": coverage.seen_count(), "s0_m2": planner.s0,
                         "rho": planner.rho, "stride": planner.stride,
                         "omega_voxels": int(planner.omega.sum())}}


def nbv_summary(result: dict) -> dict:
    """What ``report.json`` keeps of a ranking: the best view and the planner's settings."""
    best = result["best"]
    return {"best": {k: best[k] for k in ("index", "pose", "utility", "known", "unknown",
                                          "frontier_cells", "hit_fraction")},
            "n_candidates": len(result["candidates"]), "settings": result["settings"]}


def rank_run(post, cfg: Config, frames, out_dir, progress=None) -> dict:
    """Rank the candidates of ``cfg.nbv`` for a run's posterior and write ``nbv.json`` into
    ``out_dir`` (atomically); return its content. ``frames``: the run's frames (a dataset with
    ``len`` and indexing); the candidates use the first frame's intrinsics and image size."""
    from ..io import write_json

    if len(frames) == 0:
        raise DataError("no frames: the candidates need the run's intrinsics")
    first = frames[0]
    height, width = first.depth_m.shape
    result = plan(post, cfg, frames, first.K, (width, height), progress=progress)
    write_json(Path(out_dir) / "nbv.json", result)
    return result


def read_ranking(path) -> dict:
    """The content of an ``nbv.json`` (:func:`rank_run`), checked where its readers rely on
    it: a JSON object whose ``candidates`` is a non-empty list of objects, each with an
    integer ``index`` and ``rank``, a finite ``utility`` and a rigid 4x4 ``pose`` (T_W_C).
    Raises DataError naming the file and what is wrong."""
    from ..formats.readers import json_matrix, json_numbers, read_json

    path = Path(path)
    result = read_json(path, "NBV ranking")
    candidates = result.get("candidates") if isinstance(result, dict) else None
    if not isinstance(candidates, list) or not candidates:
        raise DataError(f"{path}: not an NBV ranking: it needs a non-empty list 'candidates'")
    for k, c in enumerate(candidates):
        what = f"candidate {k}"
        index, rank_, utility = json_numbers(c, ("index", "rank", "utility"), path, what)
        if not (index.is_integer() and rank_.is_integer() and math.isfinite(utility)):
            raise DataError(f"{path}: {what} needs integer index and rank and a finite "
                            f"utility, got {index}, {rank_}, {utility}")
        check_pose(json_matrix(c.get("pose"), (4, 4), path,
                               f"{what} pose"), f"{path}: {what}")
    return result


def candidates_around(post, n: int = 48, kind: str = "hemisphere", radius_scale: float = 3.0,
                      min_elevation_deg: float = 10.0, max_elevation_deg: float = 80.0):
    """``n`` candidate poses (n, 4, 4) looking at the centre of ``post``'s band from
    ``radius_scale`` times its bounding radius: ``kind`` ``hemisphere`` / ``sphere``
    (Fibonacci points between the elevations; ``sphere`` from -90 deg) or ``ring`` (at the
    centre's height). World poses."""
    lo = points_in_world(column_min(post.ijk) * post.voxel_size, post.origin)
    hi = points_in_world((column_max(post.ijk) + 1) * post.voxel_size, post.origin)
    centre, radius = 0.5 * (lo + hi), radius_scale * 0.5 * float(np.linalg.norm(hi - lo))
    if kind == "ring":
        return ring_candidates(centre, radius, n)
    if kind not in ("sphere", "hemisphere"):
        raise ConfigError(f"kind = {kind!r} is not one of hemisphere, sphere, ring")
    lo_el = -90.0 if kind == "sphere" else min_elevation_deg
    return sphere_candidates(centre, radius, n, lo_el, max_elevation_deg)


def rank(post, poses, K, image_size, config: Config | None = None, frames=None) -> list[dict]:
    """Rank candidate poses (n, 4, 4) for the posterior ``post`` with a camera ``K`` (3, 3)
    of ``image_size`` (width, height): :meth:`Planner.rank`, best first. ``config`` gives
    the observation model and NBV settings (default: the defaults); with ``frames`` (the fused
    frames) unseen space is scored too (:class:`CoverageGrid`), else known surface only."""
    cfg = config or Config()
    coverage = None
    if frames is not None:
        lo, hi = region_of_interest(post.ijk, post.voxel_size, cfg.nbv.roi_scale,
                                    origin=post.origin)
        coverage = coverage_grid(cfg, lo, hi, post.voxel_size)
        for f in frames:
            coverage.mark(f.depth_m, f.K, f.T_W_C, stride=cfg.observation.stride)
    return Planner(post, cfg, K, image_size, coverage).rank(poses)
