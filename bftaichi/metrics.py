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

from .errors import BftaichiError, DataError

__all__ = ["geometry_metrics", "load_mesh", "format_table", "DEFAULT_THRESHOLDS_MM"]

#: Default F-score thresholds (mm), as in the BayesFusion-SDF paper.
DEFAULT_THRESHOLDS_MM = (5, 10, 20, 50)


def load_mesh(path: str | os.PathLike):
    """Load a triangle mesh file (PLY, OBJ, STL, OFF, GLB, ...) as a ``trimesh.Trimesh``.

    A file holding a scene of several meshes is concatenated into one mesh (in world frame).
    Vertices are kept as stored (no merging), units as stored (bftaichi writes metres).

    Raises:
        DataError naming the path if it is missing, unreadable, or holds no triangles
        (e.g. a point cloud).
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise DataError(f"mesh file {path} does not exist")
    if not path.is_file():
        raise DataError(f"mesh file {path} is not a file")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    # trimesh's format parsers raise many exception types (ValueError, IndexError, KeyError,
    # NotImplementedError for unknown formats, struct.error, ...) on a malformed file.
    except Exception as e:  # noqa: BLE001 - re-raised as DataError naming the file
        raise DataError(f"cannot read mesh file {path}: {type(e).__name__}: {e}") from e
    if not isinstance(mesh, trimesh.Trimesh):
        raise DataError(f"mesh file {path} does not hold a triangle mesh "
                        f"(got {type(mesh).__name__})")
    if len(mesh.faces) == 0:
        raise DataError(f"mesh file {path} holds no triangles")
    if not np.all(np.isfinite(mesh.vertices)):
        raise DataError(f"mesh file {path} has non-finite vertex coordinates")
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
    from scipy.spatial import cKDTree
    from trimesh.sample import sample_surface

    _check_mesh(pred, "pred")
    _check_mesh(gt, "gt")
    try:
        thresholds = [float(t) for t in thresholds_mm]
    except (TypeError, ValueError):
        raise BftaichiError(f"thresholds_mm must be numbers (mm), got {thresholds_mm!r}") from None
    if not thresholds or not all(math.isfinite(t) and t > 0 for t in thresholds):
        raise BftaichiError(f"thresholds_mm must be positive finite numbers, got {thresholds_mm!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise BftaichiError(f"n_samples must be a positive integer, got {n_samples!r}")
    if len(gt.faces) == 0 or not gt.area > 0:
        raise BftaichiError("gt mesh has no surface (no faces or zero area)")

    n_pred_faces = int(len(pred.faces))
    if n_pred_faces == 0 or not pred.area > 0:
        d_pg = d_gp = None
    else:
        pts_p, _ = sample_surface(pred, int(n_samples), seed=seed)
        pts_g, _ = sample_surface(gt, int(n_samples), seed=seed)
        d_pg, _ = cKDTree(pts_g).query(pts_p, k=1, workers=-1)
        d_gp, _ = cKDTree(pts_p).query(pts_g, k=1, workers=-1)

    out: dict = {}
    if d_pg is None:
        out["chamfer_l2"] = math.inf
        out["accuracy_m"] = math.inf
        out["completeness_m"] = math.inf
    else:
        out["chamfer_l2"] = float(np.mean(d_pg ** 2) + np.mean(d_gp ** 2))
        out["accuracy_m"] = float(np.mean(d_pg))
        out["completeness_m"] = float(np.mean(d_gp))
    for t_mm in thresholds:
        if d_pg is None:
            precision = recall = 0.0
        else:
            t = t_mm / 1000.0
            precision = float(np.mean(d_pg < t))
            recall = float(np.mean(d_gp < t))
        fscore = 2.0 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
        out[_threshold_key("precision", t_mm)] = precision
        out[_threshold_key("recall", t_mm)] = recall
        out[_threshold_key("fscore", t_mm)] = fscore
    out["n_pred_faces"] = n_pred_faces
    return out


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
