"""A run's ``report.json`` read back, checked where its readers (``bftaichi nbv``, the viewer)
rely on it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import DataError

__all__ = ["read_report"]


def read_report(path) -> dict:
    """A run's ``report.json``, checked where its readers rely on it: a JSON object; its
    ``origin_m``, if there, 3 finite numbers; its ``cameras``, if they list poses, a pinhole
    ``K``, an ``image_size`` of two positive integers and rigid 4x4 ``poses`` (T_W_C). A failed
    run's report (``status``, ``stage``, ``error``) passes. Raises DataError naming the file and
    what is wrong."""
    from ..formats.readers import json_matrix, read_json
    from ..geometry import check_K, check_pose

    path = Path(path)
    report = read_json(path, "run report")
    if not isinstance(report, dict):
        raise DataError(f"{path}: a run report must be a JSON object, got "
                        f"{type(report).__name__}")
    if "origin_m" in report and not np.isfinite(
            json_matrix(report["origin_m"], (3,), path, "origin_m")).all():
        raise DataError(f"{path}: origin_m must be 3 finite numbers, got {report['origin_m']}")
    cameras = report.get("cameras")
    if cameras is not None and not isinstance(cameras, dict):
        raise DataError(f"{path}: cameras must be a JSON object, got {type(cameras).__name__}")
    if cameras and cameras.get("poses"):
        check_K(json_matrix(cameras.get("K"), (3, 3), path, "cameras.K"), f"{path}: cameras.K")
        size = cameras.get("image_size")
        if not (isinstance(size, list) and len(size) == 2
                and all(type(v) is int and v > 0 for v in size)):
            raise DataError(f"{path}: cameras.image_size must be [width, height] in pixels, "
                            f"got {size}")
        for k, T in enumerate(json_matrix(cameras["poses"], (-1, 4, 4), path, "cameras.poses")):
            check_pose(T, f"{path}: cameras.poses[{k}]")
    return report
