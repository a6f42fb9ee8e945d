#!/usr/bin/env python
"""Cost model of a chunked run (issue 20, item 5): from one measured chunked run, predict the
time and memory of a building-scale scene on N workers.

Input: the ``report.json`` of a ``bftaichi run`` with ``run.chunk_m`` (it records every chunk's
band voxels, frames and seconds, the stage seconds and the peak memory of each stage), e.g.::

    bftaichi run scenes/redkitchen.toml --out /tmp/rk --set run.chunk_m=2 \\
        --set run.plots=false --set run.preview=false
    python tools/chunk_cost_model.py /tmp/rk/report.json --floor-m2 2000 --plot docs/chunk_cost.png

The model, and the assumptions it rests on (printed with the prediction):

* **Per chunk**: ``t = a + b * band_voxels + c * frames`` (non-negative least squares over the
  measured chunks): a chunk's setup, its solve, and the frames it reads and observes.
* **The scene scales by its surface area**: a building of ``floor_m2`` of floor has
  ``surface_per_floor * floor_m2`` m^2 of surface (floor, ceiling, walls, furniture; default
  3), captured as densely as the measured scene (frames per m^2 of surface) at its voxel size.
  Band voxels, frames and chunks scale by ``s = surface / measured surface`` (the measured
  surface is the memory estimate's ``area_m2``); the chunks are like the measured ones (their
  mean band voxels and frames).
* **What runs on one machine (the driver)**: the TSDF integration, the whole band's build, the
  noise fit, the pass that finds each chunk's frames, the stitching, the meshes and the
  outputs: their measured seconds times ``s``, serial. Its memory: the measured peak above
  the interpreter's, times ``s`` (the TSDF, the whole band and the posterior mesh are not
  chunked).
* **On N workers** the chunks spread evenly: ``serial + ceil(chunks / N) * t_chunk``; a
  worker needs one chunk's solve in memory (the measured run's largest chunk). Ray's per-task
  overhead (milliseconds) and moving the frames to the workers (a shared file system) are left
  out.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

GIB = 2 ** 30


def fit_chunks(per_chunk: list[dict]) -> tuple[np.ndarray, float]:
    """``(a, b, c)`` of ``t = a + b voxels + c frames`` (non-negative least squares) and the
    relative RMS residual."""
    from scipy.optimize import nnls

    X = np.array([[1.0, p["band_voxels"], p["frames"]] for p in per_chunk])
    t = np.array([p["seconds"] for p in per_chunk])
    scale = X.max(axis=0)
    coef, _ = nnls(X / scale, t)
    coef = coef / scale
    rms = float(np.sqrt(np.mean((X @ coef - t) ** 2)) / np.mean(t))
    return coef, rms


def model(report: dict, floor_m2: float, surface_per_floor: float, workers: list[int]) -> dict:
    chunks = report["solver"]["map"]["chunks"]
    per = chunks["per_chunk"]
    if not per:
        raise SystemExit("the report holds no per-chunk records: run with run.chunk_m > 0")
    coef, rms = fit_chunks(per[1:] if len(per) > 3 else per)  # the first chunk pays the JIT
    sec = report["seconds"]
    chunk_total = sum(p["seconds"] for p in per)
    # the pipeline books the frames' reading apart (read_frames); the chunks' seconds hold it
    serial_posterior = sec["posterior"] + sec.get("read_frames", 0.0) - chunk_total
    serial = {"tsdf": sec["tsdf"], "export": sec.get("export", 0.0), "mesh": sec.get("mesh", 0.0),
              "posterior (band, noise fit, chunk views, stitching)": serial_posterior,
              "metrics and outputs": sec.get("metrics", 0.0) + sec.get("write", 0.0)}
    area0 = report["memory"]["estimate"]["inputs"]["area_m2"]
    surface = floor_m2 * surface_per_floor
    s = surface / area0
    mean_vox = float(np.mean([p["band_voxels"] for p in per]))
    mean_frames = float(np.mean([p["frames"] for p in per]))
    n_core = float(np.mean([p["core_voxels"] for p in per]))
    n_chunks = math.ceil(s * report["counts"]["band_voxels"] / n_core)
    t_chunk = float(coef @ [1.0, mean_vox, mean_frames])
    t_serial = s * sum(serial.values())
    peak = report["memory"]["peak_rss"]
    base = peak.get("baseline") or 0
    driver = base + s * (peak["peak"] - base)
    stages = report["memory"]["estimate"]["stages"]
    worker_bytes = max(stages["observe"], stages["map"], stages["variance"]) - (
        stages["band"] - report["memory"]["estimate"]["base_bytes"])  # one chunk, no scene
    rows = [{"workers": n, "hours": (t_serial + math.ceil(n_chunks / n) * t_chunk) / 3600}
            for n in workers]
    measured = {"frames": report["counts"]["frames"], "band_voxels": report["counts"]["band_voxels"],
                "area_m2": area0, "chunks": len(per), "chunk_side_voxels": chunks["side_voxels"],
                "halo_voxels": chunks["halo_voxels"],
                "voxel_size_m": report["tsdf"]["voxel_size_m"],
                "seconds_total": sec["total"], "seconds_chunks": chunk_total}
    return {"measured": measured, "fit": {"a_s": coef[0], "b_s_per_voxel": coef[1],
                                          "c_s_per_frame": coef[2], "relative_rms": rms},
            "serial_seconds_measured": serial, "scale": s, "surface_m2": surface,
            "frames": round(s * measured["frames"]),
            "band_voxels": round(s * measured["band_voxels"]), "chunks": n_chunks,
            "seconds_per_chunk": t_chunk, "serial_hours": t_serial / 3600,
            "chunk_hours": n_chunks * t_chunk / 3600, "driver_bytes": driver,
            "worker_bytes": worker_bytes, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="report.json of a chunked bftaichi run")
    ap.add_argument("--floor-m2", type=float, default=2000.0)
    ap.add_argument("--surface-per-floor", type=float, default=3.0,
                    help="m^2 of surface per m^2 of floor (floor, ceiling, walls, furniture)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32, 64, 128])
    ap.add_argument("--check", type=Path, nargs="*", default=[],
                    help="report.json of the same scene chunked on more workers (bftaichi "
                         "batch --workers N): its measured posterior seconds against the model's")
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    report = json.loads(args.report.read_text())
    m = model(report, args.floor_m2, args.surface_per_floor, args.workers)
    me = m["measured"]
    f = m["fit"]
    print(f"measured: {me['frames']} frames, {me['band_voxels']:,} band voxels, "
          f"{me['area_m2']:.1f} m^2 of surface, {me['voxel_size_m'] * 100:g} cm voxels, "
          f"{me['chunks']} chunks of {me['chunk_side_voxels']} voxels (halo "
          f"{me['halo_voxels']}); {me['seconds_total']:.1f} s in all, "
          f"{me['seconds_chunks']:.1f} s in chunks")
    print(f"per chunk: t = {f['a_s']:.3f} s + {f['b_s_per_voxel'] * 1e6:.2f} us x band voxels "
          f"+ {f['c_s_per_frame'] * 1e3:.1f} ms x frames (relative RMS residual "
          f"{100 * f['relative_rms']:.0f} %)")
    print("serial (driver) seconds measured: " + ", ".join(
        f"{k} {v:.1f}" for k, v in m["serial_seconds_measured"].items()))
    # the model's own check: the measured scene on 1 worker (and more, with --check)
    one = m["serial_hours"] / m["scale"] * 3600 + sum(
        float(np.dot([f["a_s"], f["b_s_per_voxel"], f["c_s_per_frame"]],
                     [1, p["band_voxels"], p["frames"]]))
        for p in report["solver"]["map"]["chunks"]["per_chunk"])
    print(f"model on the measured scene, 1 worker: {one:.1f} s (measured "
          f"{sum(m['serial_seconds_measured'].values()) + me['seconds_chunks']:.1f} s)")
    for path in args.check:
        other = json.loads(path.read_text())
        per = other["solver"]["map"]["chunks"]["per_chunk"]
        workers = len({p["worker"] for p in per})
        pred = (m["serial_seconds_measured"]["posterior (band, noise fit, chunk views, stitching)"]
                + me["seconds_chunks"] / max(1, workers))
        print(f"check {path}: chunks on {workers} worker processes: posterior "
              f"{other['seconds']['posterior']:.1f} s measured, ~{pred:.1f} s if the chunks "
              "split evenly")
    print(f"\npredicted: {args.floor_m2:g} m^2 of floor x {args.surface_per_floor:g} = "
          f"{m['surface_m2']:.0f} m^2 of surface (x{m['scale']:.0f} the measured scene): "
          f"{m['frames']:,} frames, {m['band_voxels'] / 1e6:.0f} M band voxels, "
          f"{m['chunks']:,} chunks of {m['seconds_per_chunk']:.1f} s")
    print(f"serial part {m['serial_hours']:.2f} h on the driver, chunks {m['chunk_hours']:.1f} "
          f"worker-hours; driver memory ~{m['driver_bytes'] / GIB:.0f} GiB, per worker "
          f"~{m['worker_bytes'] / GIB:.2f} GiB")
    for r in m["rows"]:
        print(f"  {r['workers']:4d} workers: {r['hours']:7.2f} h")
    if args.json:
        args.json.write_text(json.dumps(m, indent=1, default=float))
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        w = [r["workers"] for r in m["rows"]]
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.loglog(w, [r["hours"] for r in m["rows"]], "o-", label="predicted")
        ax.axhline(m["serial_hours"], color="grey", ls="--", label="serial part (driver)")
        ax.set_xlabel("Ray workers (1 CPU each)")
        ax.set_ylabel("hours")
        ax.set_title(f"{args.floor_m2:g} m$^2$ of floor at {me['voxel_size_m'] * 100:g} cm, "
                     f"chunks of {me['chunk_side_voxels']} voxels", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(args.plot, dpi=120)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
