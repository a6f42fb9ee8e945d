"""Geometry metrics of a reconstructed mesh against a ground-truth mesh (DESIGN.md section 6).

Both surfaces are sampled area-uniformly with a fixed seed, and each sample is matched to its
nearest sample on the other surface (``scipy.spatial.cKDTree``). With P the predicted samples, G
the ground-truth samples and ``d(x, S)`` the distance to the nearest sample of S (metres):

- Chamfer (L2): ``CD = mean_P d(p, G)^2 + mean_G d(g, P)^2``  (m^2)
- accuracy ``Acc = mean_P d(p, G)``, completeness ``Comp = mean_G d(g, P)``  (m)
- ``precision@t = frac_P(d(p, G) < t)``, ``recall@t = frac_G(d(g, P) < t)``,
  ``F@t = 2 P R / (P + R)`` (0 when both are 0), thresholds t in millimetres.

Sample-to-sample distances over-estimate surface-to-surface distances by about the sample spacing
(``sqrt(area / n_samples)``, 0.7 mm for 0.1 m^2 and the default 200 000 samples): keep it well
below the smallest threshold.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import BftaichiError, DataError

__all__ = ["geometry_metrics", "surface_distances", "surface_distances_many",
           "surface_sdf", "SampledSurface", "SurfaceSDF",
           "uncertainty_metrics", "spearman",
           "load_mesh", "check_mesh_file", "format_table", "DEFAULT_THRESHOLDS_MM",
           "near_surface_voxels", "band_sdf", "band_uncertainty", "vertex_errors",
           "vertex_uncertainty"]

#: Default F-score thresholds (mm), as in the BayesFusion-SDF paper.
DEFAULT_THRESHOLDS_MM = (5, 10, 20, 50)


def load_mesh(path: str | os.PathLike, surface: bool = False):
    """Load a triangle mesh file (PLY, OBJ, STL, OFF, GLB, ...) as a ``trimesh.Trimesh``.

    A file holding a scene of several meshes is concatenated into one mesh (in world frame).
    Vertices are kept as stored (no merging), units as stored (bftaichi writes metres).
    ``surface``: the mesh must also have a positive area (a ground truth to measure against).

    Raises:
        DataError naming the path if it is missing or unreadable, or its content fails
        :func:`check_mesh_file`.
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise DataError(f"mesh file {path} does not exist")
    if not path.is_file():
        raise DataError(f"mesh file {path} is not a file")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    # trimesh's format parsers raise many exception types on a malformed file (ValueError,
    # IndexError, KeyError, struct.error; an unknown file type raises its own error too)
    except Exception as e:  # noqa: BLE001 - re-raised as DataError naming the file
        raise DataError(f"cannot read mesh file {path}: {type(e).__name__}: {e}") from e
    return check_mesh_file(mesh, path, surface)


def check_mesh_file(mesh, path, surface: bool = False):
    """``mesh``, read from file ``path``, if it is a usable triangle mesh: a
    ``trimesh.Trimesh`` with triangles, finite vertex coordinates, face indices in
    ``0..V-1`` and a finite surface area (positive with ``surface``). Else DataError naming
    the file and what is wrong (e.g. a point cloud, NaN coordinates, a damaged face list)."""
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise DataError(f"mesh file {path} does not hold a triangle mesh "
                        f"(got {type(mesh).__name__})")
    if len(mesh.faces) == 0:
        raise DataError(f"mesh file {path} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise DataError(f"mesh file {path} has non-finite vertex coordinates")
    lo, hi = int(mesh.faces.min()), int(mesh.faces.max())
    if lo < 0 or hi >= len(mesh.vertices):
        raise DataError(f"mesh file {path}: face vertex indices span {lo}..{hi} but the mesh "
                        f"has {len(mesh.vertices)} vertices")
    if not np.isfinite(mesh.area):
        raise DataError(f"mesh file {path}: the surface area overflows (coordinates too large)")
    if surface and not mesh.area > 0:
        raise DataError(f"mesh file {path} has no surface: every triangle has zero area")
    return mesh


def _check_mesh(mesh, name: str):
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh):
        raise BftaichiError(f"{name} must be a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) and not np.all(np.isfinite(mesh.vertices)):
        raise BftaichiError(f"{name} mesh has non-finite vertex coordinates")


def _threshold_key(kind: str, t_mm: float) -> str:
    return f"{kind}@{t_mm:g}mm"


def geometry_metrics(pred, gt, thresholds_mm=DEFAULT_THRESHOLDS_MM, n_samples: int = 200_000,
                     seed: int = 0) -> dict:
    """Chamfer, accuracy, completeness and precision/recall/F-score of ``pred`` against ``gt``.

    Args:
        pred: predicted ``trimesh.Trimesh`` (metres). May be empty (no faces).
        gt: ground-truth ``trimesh.Trimesh`` (metres, same world frame); must have surface area.
        thresholds_mm: distance thresholds in millimetres (positive).
        n_samples: points sampled on each surface, area-weighted.
        seed: sampling seed; both meshes are sampled with it, so identical meshes give identical
            samples and zero distance.

    Returns:
        A flat JSON-ready dict, in this order: ``chamfer_l2`` (m^2), ``accuracy_m``,
        ``completeness_m`` (m), then ``precision@{t:g}mm``, ``recall@...``, ``fscore@...`` per
        threshold, then ``n_pred_faces``. An empty (or zero-area) prediction gives inf for the
        distances and 0 for the ratios.

    Raises:
        BftaichiError (a ValueError) if ``gt`` has no surface, or an argument is invalid.
    """
    _check_mesh(pred, "pred")
    _check_mesh(gt, "gt")
    try:
        thresholds = [float(t) for t in thresholds_mm]
    except (TypeError, ValueError):
        raise BftaichiError(f"thresholds_mm must be numbers (mm), got {thresholds_mm!r}") from None
    if not thresholds or not all(math.isfinite(t) and t > 0 for t in thresholds):
        raise BftaichiError(f"thresholds_mm must be positive finite numbers, got {thresholds_mm!r}")

    return metrics_from_distances(surface_distances(pred, gt, n_samples, seed), thresholds,
                                  int(len(pred.faces)))


def metrics_from_distances(distances, thresholds_mm, n_pred_faces: int) -> dict:
    """:func:`geometry_metrics` from the distances of :func:`surface_distances` (None: an
    empty prediction), for callers that keep the distances (the run's plots)."""
    out: dict = {}
    if distances is None:
        out["chamfer_l2"] = math.inf
        out["accuracy_m"] = math.inf
        out["completeness_m"] = math.inf
    else:
        d_pg, d_gp = distances
        out["chamfer_l2"] = float(np.mean(d_pg ** 2) + np.mean(d_gp ** 2))
        out["accuracy_m"] = float(np.mean(d_pg))
        out["completeness_m"] = float(np.mean(d_gp))
    thresholds = [float(t) for t in thresholds_mm]
    if distances is None:
        zeros = np.zeros(len(thresholds))
        curves = {"precision": zeros, "recall": zeros, "fscore": zeros}
    else:
        curves = threshold_curves(*distances, thresholds)
    for k, t_mm in enumerate(thresholds):
        for kind in ("precision", "recall", "fscore"):
            out[_threshold_key(kind, t_mm)] = float(curves[kind][k])
    out["n_pred_faces"] = int(n_pred_faces)
    return out


def threshold_curves(d_pg: np.ndarray, d_gp: np.ndarray, thresholds_mm) -> dict:
    """Precision, recall and F-score at each threshold, from the two distance arrays of
    :func:`surface_distances` (metres): ``precision(t) = frac(d_pg < t)``, ``recall(t) =
    frac(d_gp < t)``, ``F = 2 P R / (P + R)`` (0 when both are 0), ``t = t_mm / 1000``.

    Returns ``{"threshold_mm", "precision", "recall", "fscore"}``, float64 arrays of the
    thresholds' length (non-decreasing in the threshold for ascending thresholds).
    """
    d_pg = np.sort(np.asarray(d_pg, np.float64).ravel())
    d_gp = np.sort(np.asarray(d_gp, np.float64).ravel())
    t_mm = np.asarray(thresholds_mm, np.float64).ravel()
    if len(d_pg) == 0 or len(d_gp) == 0:
        raise BftaichiError("threshold_curves needs non-empty distance arrays")
    t = t_mm / 1000.0
    # searchsorted(..., "left") counts the distances strictly below t: the count of d < t.
    precision = np.searchsorted(d_pg, t, side="left") / len(d_pg)
    recall = np.searchsorted(d_gp, t, side="left") / len(d_gp)
    total = precision + recall
    fscore = np.divide(2.0 * precision * recall, total, out=np.zeros_like(total), where=total > 0)
    return {"threshold_mm": t_mm, "precision": precision, "recall": recall, "fscore": fscore}


def surface_distances(pred, gt, n_samples: int = 200_000,
                      seed: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """The sample-to-sample distances behind :func:`geometry_metrics`: ``n_samples`` points
    sampled area-uniformly on each mesh with ``seed``, each matched to the nearest sample of the
    other mesh.

    Returns ``(d_pg, d_gp)``, two (n_samples,) float64 arrays in metres (``d_pg``: each
    predicted sample to the ground truth, the accuracy side; ``d_gp``: each ground-truth sample
    to the prediction, the completeness side), or None when ``pred`` has no surface (no faces or
    zero area).

    Raises:
        BftaichiError (a ValueError) if ``gt`` has no surface, or an argument is invalid.
    """
    return surface_distances_many([pred], gt, n_samples, seed)[0]


def surface_distances_many(preds, gt, n_samples: int = 200_000, seed: int = 0) -> list:
    """:func:`surface_distances` of each mesh of ``preds`` against one ``gt``, which is sampled
    and indexed once for all of them (the same values as separate calls)."""
    for pred in preds:
        _check_mesh(pred, "pred")
    target = SampledSurface(gt, n_samples, seed)
    return [target.distances(pred) for pred in preds]


class SampledSurface:
    """A ground-truth mesh sampled area-uniformly (``n_samples`` points, ``seed``) and indexed
    once, lazily (a k-d tree), for :meth:`distances` of any number of meshes to it: the values
    of :func:`surface_distances`. Safe to use from one thread at a time.

    Raises:
        BftaichiError (a ValueError) if ``gt`` has no surface, or an argument is invalid.
    """

    def __init__(self, gt, n_samples: int = 200_000, seed: int = 0):
        _check_mesh(gt, "gt")
        if (isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer))
                or n_samples < 1):
            raise BftaichiError(f"n_samples must be a positive integer, got {n_samples!r}")
        if len(gt.faces) == 0 or not gt.area > 0:
            raise BftaichiError("gt mesh has no surface (no faces or zero area)")
        self.gt, self.n_samples, self.seed = gt, int(n_samples), seed
        self._points = self._tree = None

    def index(self) -> None:
        """Sample and index the ground truth now (otherwise at the first :meth:`distances`)."""
        if self._tree is None:
            from scipy.spatial import cKDTree
            from trimesh.sample import sample_surface

            self._points, _ = sample_surface(self.gt, self.n_samples, seed=self.seed)
            self._tree = cKDTree(self._points)

    def points(self) -> np.ndarray:
        """The (n_samples, 3) ground-truth samples (sampled now if not yet)."""
        self.index()
        return self._points

    def chamfer_split(self, pred, mask: np.ndarray, *,
                      matched=None) -> tuple[float, float] | None:
        """``chamfer_l2`` of ``pred`` split by the ground-truth samples' ``mask`` (n_samples,)
        bool: ``(part where mask, part elsewhere)``, each ``(sum d_pg^2 + sum d_gp^2) /
        n_samples`` over its samples, a predicted sample counting with the class of the
        ground-truth sample nearest to it; the two add up to :func:`geometry_metrics`'
        ``chamfer_l2`` (the same samples). ``matched``: :meth:`match` of ``pred`` when the
        caller already has it. None when ``pred`` has no surface."""
        mask = np.asarray(mask, bool)
        if mask.shape != (self.n_samples,):
            raise BftaichiError(f"mask must have shape ({self.n_samples},), got {mask.shape}")
        if matched is None:
            matched = self.match(pred)
        if matched is None:
            return None
        d_pg, nearest, d_gp = matched
        p_in = mask[nearest]
        inside = (np.sum(d_pg[p_in] ** 2) + np.sum(d_gp[mask] ** 2)) / self.n_samples
        outside = (np.sum(d_pg[~p_in] ** 2) + np.sum(d_gp[~mask] ** 2)) / self.n_samples
        return float(inside), float(outside)

    def distances(self, pred) -> tuple[np.ndarray, np.ndarray] | None:
        """``(d_pg, d_gp)`` of ``pred`` (:func:`surface_distances`), None when ``pred`` has no
        surface."""
        matched = self.match(pred)
        return None if matched is None else (matched[0], matched[2])

    def match(self, pred):
        """``(d_pg, nearest, d_gp)``: ``pred``'s samples' distances to the ground truth's and
        the index of the nearest (into :meth:`points`), and the ground truth's samples'
        distances to ``pred``'s; None when ``pred`` has no surface."""
        from scipy.spatial import cKDTree
        from trimesh.sample import sample_surface

        _check_mesh(pred, "pred")
        if len(pred.faces) == 0 or not pred.area > 0:
            return None
        self.index()
        pts_p, _ = sample_surface(pred, self.n_samples, seed=self.seed)
        d_pg, nearest = self._tree.query(pts_p, k=1, workers=-1)
        d_gp, _ = cKDTree(pts_p).query(self._points, k=1, workers=-1)
        return d_pg, nearest, d_gp


# --------------------------------------------------------------------------------------------
# uncertainty
# --------------------------------------------------------------------------------------------

def surface_sdf(mesh, points: np.ndarray, spacing_m: float, seed: int = 0,
                max_samples: int = 4_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of ``points`` to ``mesh`` near its surface (positive on the side its face
    normals point to, i.e. outside for a consistently wound mesh), for judging an SDF estimate.

    The mesh is sampled area-uniformly about every ``spacing_m`` (fixed seed); each point takes
    the plane of its nearest sample, ``phi = <x - s, n_face(s)>``. Where the surface is locally
    flat this is exact; on a surface of curvature k its error is about ``k t^2 / 2`` for a
    lateral offset ``t <= spacing_m``, i.e. below 0.02 mm for a 5 mm radius and 0.5 mm spacing.
    A point is *invalid* (``valid`` False) where the sign is not defined by the mesh: its nearest
    sample lies within ``2 spacing_m + |phi|`` of an open boundary edge (the plane's extension
    beyond a hole says nothing), or it has no finite coordinates.

    Args:
        mesh: ground-truth ``trimesh.Trimesh`` with surface area (metres).
        points: (M, 3) query points, metres.
        spacing_m: sample spacing on the surface, metres (> 0).
        seed: sampling seed.
        max_samples: the spacing is coarsened so at most this many samples are drawn.

    Returns:
        ``phi`` (M,) float64 metres and ``valid`` (M,) bool.
    """
    return SurfaceSDF(mesh, spacing_m, seed, max_samples)(points)


class SurfaceSDF:
    """:func:`surface_sdf` with the mesh sampled and indexed once (for many point sets, or ahead
    of the points): ``SurfaceSDF(mesh, spacing_m, seed, max_samples)(points) -> (phi, valid)``,
    the same values. Safe to call from one thread at a time."""

    def __init__(self, mesh, spacing_m: float, seed: int = 0, max_samples: int = 4_000_000):
        from scipy.spatial import cKDTree
        from trimesh.sample import sample_surface

        _check_mesh(mesh, "mesh")
        if len(mesh.faces) == 0 or not mesh.area > 0:
            raise BftaichiError("mesh has no surface (no faces or zero area)")
        if not (math.isfinite(spacing_m) and spacing_m > 0):
            raise BftaichiError(f"spacing_m must be a positive number, got {spacing_m!r}")
        n = int(min(max_samples, max(1000, math.ceil(mesh.area / spacing_m ** 2))))
        self.spacing = math.sqrt(mesh.area / n)
        self.samples, face = sample_surface(mesh, n, seed=seed)
        self.normals = np.asarray(mesh.face_normals)[face]
        self.tree = cKDTree(self.samples)
        # Open boundary: edges used by one face only (the mesh's own vertex indexing; a mesh
        # with duplicated vertices at seams shows spurious boundaries there, which only drops
        # points).
        edges = np.sort(np.asarray(mesh.edges, np.int64), axis=1)
        n_v = max(len(mesh.vertices), 1)
        # one int64 key per edge (ascending keys = lexicographic edges): np.unique's result,
        # without its row sort
        keys, count = np.unique(edges[:, 0] * n_v + edges[:, 1], return_counts=True)
        uniq = np.stack([keys // n_v, keys % n_v], axis=1)
        boundary = uniq[count == 1]
        self.edge_tree = None
        if len(boundary):
            verts = np.asarray(mesh.vertices)
            a, b = verts[boundary[:, 0]], verts[boundary[:, 1]]
            # Points along the boundary edges, spaced below the sample spacing.
            steps = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / self.spacing)
                               ).astype(int)
            t = np.concatenate([np.arange(k + 1) / k for k in steps])
            edge_pts = np.repeat(a, steps + 1, axis=0) + t[:, None] * np.repeat(
                b - a, steps + 1, axis=0)
            self.edge_tree = cKDTree(edge_pts)

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points = np.asarray(points, np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(points), axis=1)
        phi = np.zeros(len(points))
        valid = finite.copy()
        if not finite.any():
            return phi, valid
        _, nearest = self.tree.query(points[finite], k=1, workers=-1)
        phi[finite] = np.einsum("ij,ij->i", points[finite] - self.samples[nearest],
                                self.normals[nearest])
        if self.edge_tree is not None:
            d_edge, _ = self.edge_tree.query(self.samples[nearest], k=1, workers=-1)
            idx = np.flatnonzero(finite)
            valid[idx] = d_edge > 2 * self.spacing + np.abs(phi[idx])
        return phi, valid


def uncertainty_metrics(mean: np.ndarray, sigma: np.ndarray, truth: np.ndarray,
                        n_bins: int = 20) -> dict:
    """How honest is ``sigma`` about the error ``e = mean - truth`` (DESIGN.md section 6)?

    Returns a JSON-ready dict:

    - ``n``; ``rms_error_m``; ``mean_error_m``; ``median_error_m``; ``median_sigma_m``;
    - ``coverage@1sigma``, ``@2sigma``, ``@3sigma``: fraction with ``|e| <= k sigma`` (a
      Gaussian gives 0.683 / 0.954 / 0.997);
    - ``median_z``: median of ``|e| / sigma`` (0.674 for a Gaussian; above, sigma is
      overconfident; below, conservative);
    - ``nll``: mean Gaussian negative log-likelihood of ``e`` under ``N(0, sigma^2)`` (nats), and
      ``nll_vs_constant``: ``nll`` minus the NLL under the best constant sigma chosen with
      hindsight, ``sqrt(mean e^2)``. Below 0, sigma tells more than one number would
      (informative); above, a constant would have served the user better;
    - ``spearman``: rank correlation of sigma with ``|e|`` (> 0: sigma ranks the errors);
    - ``sparsification``: mean ``|e|`` of what is left after removing the fraction
      ``i / n_bins`` (i = 0..n_bins-1) most uncertain values, and ``ause``: its mean gap over
      the oracle curve that removes the largest errors first (metres, 0 is perfect ranking);
    - ``top10_ratio``: mean ``|e|`` of the 10 % most uncertain values over the mean ``|e|`` of
      all (1 when sigma says nothing about where the errors are; higher is better).

    Raises:
        BftaichiError: different lengths, fewer than 2 values, or non-finite input.
    """
    mean, sigma, truth = (np.asarray(a, np.float64).ravel() for a in (mean, sigma, truth))
    if not (len(mean) == len(sigma) == len(truth)):
        raise BftaichiError(f"mean, sigma and truth must have one length, got {len(mean)}, "
                            f"{len(sigma)}, {len(truth)}")
    if len(mean) < 2:
        raise BftaichiError("uncertainty_metrics needs at least 2 values")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(sigma)) and
            np.all(np.isfinite(truth))):
        raise BftaichiError("uncertainty_metrics: mean, sigma and truth must be finite")
    err = np.abs(mean - truth)
    tiny = np.finfo(np.float64).tiny
    sigma = np.maximum(sigma, tiny)
    z = err / sigma
    n = len(err)
    out = {"n": int(n), "rms_error_m": float(np.sqrt(np.mean(err ** 2))),
           "mean_error_m": float(err.mean()), "median_error_m": float(np.median(err)),
           "median_sigma_m": float(np.median(sigma))}
    for k in (1, 2, 3):
        out[f"coverage@{k}sigma"] = float(np.mean(z <= k))
    out["median_z"] = float(np.median(z))
    half_log_2pi = 0.5 * math.log(2 * math.pi)
    nll = float(np.mean(np.log(sigma) + 0.5 * z * z) + half_log_2pi)
    const = max(float(np.sqrt(np.mean(err ** 2))), tiny)
    out["nll"] = nll
    out["nll_vs_constant"] = nll - (math.log(const) + 0.5 + half_log_2pi)
    out["spearman"] = spearman(sigma, err)

    def sparsification(order):
        # mean |e| of the values kept after removing the first fraction f of ``order``
        tail = np.cumsum(err[order][::-1])[::-1]
        start = (np.arange(n_bins) / n_bins * n).astype(int)
        return tail[start] / (n - start)

    by_sigma = sparsification(np.argsort(-sigma, kind="stable"))
    oracle = sparsification(np.argsort(-err, kind="stable"))
    out["sparsification"] = [float(v) for v in by_sigma]
    out["ause"] = float(np.mean(by_sigma - oracle))
    top = np.argsort(-sigma, kind="stable")[:max(1, n // 10)]
    out["top10_ratio"] = float(err[top].mean() / max(err.mean(), tiny))
    return out


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of ``a`` and ``b`` (1-D, one length): the Pearson correlation
    of their ranks, tied values sharing their mean rank (``scipy.stats.spearmanr``'s statistic,
    tests/test_metrics.py); 0 where either is constant. Here rather than scipy.stats, whose
    import costs ~0.5 s of every run that has a ground truth."""
    ra, rb = _ranks(a), _ranks(b)
    ra -= ra.mean()
    rb -= rb.mean()
    den = math.sqrt(float(ra @ ra) * float(rb @ rb))
    return float(ra @ rb) / den if den > 0 else 0.0


def _ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of ``x`` (float64), ties given their mean rank."""
    x = np.asarray(x, np.float64).ravel()
    order = np.argsort(x, kind="stable")
    first = np.r_[True, x[order][1:] != x[order][:-1]]  # the first of each run of ties
    start = np.flatnonzero(first)
    mean_rank = start + 0.5 * (np.diff(np.r_[start, len(x)]) - 1) + 1
    ranks = np.empty(len(x))
    ranks[order] = mean_rank[np.cumsum(first) - 1]
    return ranks


def vertex_errors(vertices: np.ndarray, gt) -> np.ndarray:
    """The exact distance (metres) of each vertex to the ground-truth mesh ``gt``: the
    point-to-triangle distance to its closest triangle (libigl's AABB tree), i.e. ``|phi_true|``
    at the vertex, where the posterior mean is 0 (DESIGN.md section 6). No sampling floor."""
    import igl

    _check_mesh(gt, "gt")
    v = np.ascontiguousarray(np.asarray(vertices, np.float64).reshape(-1, 3))
    if len(v) == 0:
        return np.zeros(0)
    d2, _, _ = igl.point_mesh_squared_distance(
        v, np.ascontiguousarray(gt.vertices, dtype=np.float64),
        np.ascontiguousarray(gt.faces, dtype=np.int64))
    return np.sqrt(np.maximum(d2, 0.0))


def vertex_uncertainty(mesh, gt, attribute: str = "sigma", errors=None) -> dict | None:
    """Calibration of the vertex ``attribute`` (default ``sigma``, metres) of ``mesh`` (a
    ``trimesh.Trimesh`` with ``vertex_attributes``) against its exact vertex errors
    (:func:`vertex_errors`, or ``errors`` when the caller computed them already):
    :func:`uncertainty_metrics` with ``e = |phi_true(v)|``. None when the mesh has fewer than 2
    vertices."""
    sigma = np.asarray(mesh.vertex_attributes[attribute], np.float64)
    if len(sigma) < 2:
        return None
    err = vertex_errors(mesh.vertices, gt) if errors is None else np.asarray(errors, np.float64)
    return uncertainty_metrics(err, sigma, np.zeros_like(err))


# --------------------------------------------------------------------------------------------
# table
# --------------------------------------------------------------------------------------------

_RATIO_PREFIXES = ("precision@", "recall@", "fscore@")


def _label(key: str) -> str:
    if key == "chamfer_l2":
        return "chamfer_l2 [m^2]"
    if key.endswith("_m"):
        return f"{key[:-2]} [mm]"
    return key


def _format_value(key: str, value) -> str:
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        if key == "chamfer_l2":
            return f"{v:.3e}"
        if key.endswith("_m"):
            return f"{v * 1000.0:.2f}"
        if key.startswith(_RATIO_PREFIXES):
            return f"{v:.3f}"
        return f"{v:.4g}"
    return str(value)


def format_table(rows: dict[str, dict], keys: list[str] | None = None) -> str:
    """Plain-text table: one column per entry of ``rows`` (e.g. ``{"tsdf_mesh.ply": m1,
    "mesh.ply": m2}``), one line per metric.

    ``keys`` selects and orders the metrics (default: every key of the rows, in first-seen
    order). Chamfer is shown in scientific notation (m^2), ``*_m`` distances in millimetres with
    2 decimals (label ``accuracy [mm]``), precision/recall/F-score with 3 decimals, integers as
    is; a metric a row lacks shows ``-``. Returns the table without a trailing newline.
    """
    if not isinstance(rows, dict):
        raise BftaichiError(f"rows must be a dict of name -> metrics dict, got {type(rows).__name__}")
    for name, metrics in rows.items():
        if not isinstance(metrics, dict):
            raise BftaichiError(f"rows[{name!r}] must be a dict of metrics, "
                                f"got {type(metrics).__name__}")
    if keys is None:
        keys = list(dict.fromkeys(k for metrics in rows.values() for k in metrics))
    names = [str(n) for n in rows]
    labels = [_label(k) for k in keys]
    cells = [[_format_value(k, metrics.get(k)) for metrics in rows.values()] for k in keys]

    label_w = max([len("metric")] + [len(s) for s in labels])
    col_w = [max([len(n)] + [len(line[j]) for line in cells]) for j, n in enumerate(names)]
    header = "  ".join(["metric".ljust(label_w)] + [n.rjust(w) for n, w in zip(names, col_w)])
    lines = [header, "-" * len(header)]
    for label, line in zip(labels, cells):
        lines.append("  ".join([label.ljust(label_w)] + [c.rjust(w) for c, w in zip(line, col_w)]))
    return "\n".join(lines)


def near_surface_voxels(post, gt, near_voxels: float = 1.0, seed: int = 0, sdf=None):
    """``(mean, sigma, phi)`` of the observed band voxels (bootstrap weight > 0) within
    ``near_voxels`` voxels of the ground-truth surface ``gt`` (world coordinates), ``phi`` their
    true signed distance (:func:`bftaichi.evaluation.metrics.surface_sdf`, sampled every
    voxel / 4, computed in the posterior's local frame; ``sdf``: that :class:`SurfaceSDF`,
    prepared by the caller, in place of ``gt``); None when fewer than 2 voxels qualify."""
    vs = post.voxel_size
    centres = (post.ijk.astype(np.float64) + 0.5) * vs
    if sdf is None:
        sdf = band_sdf(gt, post.origin, vs, seed)
    phi, valid = sdf(centres)
    near = valid & (post.weight > 0) & (np.abs(phi) <= near_voxels * vs)
    if np.count_nonzero(near) < 2:
        return None
    return post.mean[near], post.sigma[near], phi[near]


def band_sdf(gt, origin, voxel_size_m: float, seed: int = 0) -> SurfaceSDF:
    """The :class:`SurfaceSDF` :func:`near_surface_voxels` judges a band with: ``gt`` (world
    coordinates) in the local frame at ``origin``, sampled every ``voxel_size_m / 4``."""
    from ..geometry import mesh_in_local

    return SurfaceSDF(mesh_in_local(gt, origin), voxel_size_m / 4, seed)


def band_uncertainty(post, gt, near_voxels: float = 1.0, seed: int = 0,
                     sdf=None) -> dict | None:
    """Calibration of the posterior against the ground-truth surface (DESIGN.md section 6):
    :func:`bftaichi.evaluation.metrics.uncertainty_metrics` of ``post.mean`` and ``post.sigma`` against the
    true signed distance over :func:`near_surface_voxels` (``sdf``: its prepared
    :func:`band_sdf`). None when fewer than 2 voxels qualify."""
    near = near_surface_voxels(post, gt, near_voxels, seed, sdf)
    if near is None:
        return None
    out = uncertainty_metrics(*near)
    out["near_voxels"] = near_voxels
    return out
