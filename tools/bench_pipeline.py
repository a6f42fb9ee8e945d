#!/usr/bin/env python
"""The whole probabilistic pipeline against Open3D's TSDF-only pipeline, side by side, whole
processes, on real frames (issue 16's targets).

    python tools/bench_pipeline.py                          # 500 redkitchen frames, 2 cm and 1 cm
    python tools/bench_pipeline.py --voxels 0.02 --frames 100 --repeats 1
    python tools/bench_pipeline.py --set observation.model=voxels   # the per-voxel data term

For each voxel size, in one run, alternating ``--repeats`` times (the best of each is kept):

* **bftaichi**: ``bftaichi fuse DATA --voxel V --frames 0:N --out TMP -q``, every output
  (meshes, band.npz, report, plots, preview), as a child process: wall seconds, peak
  resident memory (the larger of ``wait4``'s and the per-stage peaks of its report.json:
  ``fuse`` resets the kernel's peak counter per stage, so ``wait4`` alone sees only the last
  stages) and the stage seconds of its report.json.
* **Open3D**: a child process doing what an Open3D user's TSDF-only script does: read the
  depth PNGs and poses (``o3d.t.io.read_image``), integrate them into a tensor
  ``VoxelBlockGrid`` (CPU:0, 8^3 blocks, float32 tsdf and weight, truncation 4 voxels: the
  TSDF truncation ``alpha tau`` that ``fuse`` uses, depth cut at 6 m like ``fuse``), extract
  the triangle mesh and write it as PLY.

Printed ratios, each against its target:

* observation passes (``observe`` + ``misfit`` of report.json: every pass over the frames'
  pixels the posterior makes) / TSDF integration (``tsdf``): at most 1.5;
* MAP + variance (``map`` + ``bias`` + ``variance``: the MAP, and step 6's solves, the prior
  bias's and the probes') / TSDF integration: at most 1.0 (before 2026-12-05 the ratio left
  ``bias`` out, and the stage table did not print it);
* whole ``fuse`` / whole Open3D process: at most 3;
* peak memory of ``fuse`` / Open3D's: at most 2.

TSDF integration against Open3D's, kernel to kernel, is ``tools/bench_tsdf.py``; cold and
warm start of ``bftaichi run`` is ``tools/bench_startup.py``. The machine may be shared: both
sides run interleaved and the best of ``--repeats`` is reported (all runs are printed).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import checkout  # noqa: E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"
DEPTH_MAX_M = 6.0  # fuse's default scene.depth_max_m
TRUNC_VOXELS = 4.0  # fuse's TSDF truncation: alpha (2) x tau (2 voxels)
TARGETS = {"observe/tsdf": 1.5, "map+variance/tsdf": 1.0, "fuse/open3d": 3.0,
           "memory fuse/open3d": 2.0}


def open3d_child(data: Path, voxel: float, n: int, out: Path) -> int:
    """The Open3D side, run in its own process: read, integrate, extract, write."""
    import numpy as np
    import open3d as o3d
    import open3d.core as o3c

    K = np.loadtxt(data / "camera-intrinsics.txt").reshape(3, 3)
    names = sorted(p.name[: -len(".depth.png")] for p in data.glob("frame-*.depth.png"))[:n]
    intrinsic = o3c.Tensor(K, o3c.float64)
    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)), voxel_size=voxel, block_resolution=8, block_count=50_000,
        device=o3c.Device("CPU:0"))
    for name in names:
        depth = o3d.t.io.read_image(str(data / f"{name}.depth.png"))
        raw = depth.as_tensor().numpy()
        raw[raw == 65535] = 0  # 7-Scenes' "no measurement" code
        depth = o3d.t.geometry.Image(o3c.Tensor(raw))
        extrinsic = o3c.Tensor(np.linalg.inv(np.loadtxt(data / f"{name}.pose.txt")),
                               o3c.float64)
        blocks = vbg.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1000.0,
                                                      DEPTH_MAX_M, TRUNC_VOXELS)
        vbg.integrate(blocks, depth, intrinsic, extrinsic, 1000.0, DEPTH_MAX_M, TRUNC_VOXELS)
    mesh = vbg.extract_triangle_mesh()
    out.mkdir(parents=True, exist_ok=True)
    o3d.t.io.write_triangle_mesh(str(out / "mesh.ply"), mesh)
    print(json.dumps({"frames": len(names), "vertices": int(mesh.vertex.positions.shape[0])}))
    return 0


def timed(cmd: list[str]) -> dict:
    """Run ``cmd``; its wall seconds, peak resident memory (MiB) and exit code."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=checkout.child_env())  # this checkout's bftaichi
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    out, err = proc.stdout.read(), proc.stderr.read()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err[-2000:]}")
    return {"seconds": seconds, "peak_mib": usage.ru_maxrss / 1024.0, "stdout": out}


def _report_peak_mib(report: dict) -> float:
    """The highest per-stage peak RSS ``fuse`` measured of itself (report.json
    ``memory.peak_rss.peak``), MiB. ``fuse`` resets the kernel's peak counter at every stage
    (:class:`bftaichi.running.resources.PeakRSS`), which also resets the ``ru_maxrss`` that
    ``wait4`` reports: that one alone covers only the stages after the last reset. The larger
    of the two is the process's peak (what runs between two stages is not covered)."""
    peak = ((report.get("memory") or {}).get("peak_rss") or {}).get("peak")
    return 0.0 if peak is None else peak / 2.0 ** 20


def bench_voxel(data: Path, voxel: float, n: int, repeats: int, tmp: Path,
                sets: tuple = ()) -> dict:
    fuse_runs, o3d_runs, stages = [], [], None
    extra = [a for s in sets for a in ("--set", s)]
    for r in range(repeats):
        out = tmp / f"fuse-{voxel}-{r}"
        run = timed([sys.executable, "-m", "bftaichi.cli", "fuse", str(data), "--voxel",
                     str(voxel), "--frames", f"0:{n}", "--out", str(out), "-q", *extra])
        report = json.loads((out / "report.json").read_text())
        run["peak_mib"] = max(run["peak_mib"], _report_peak_mib(report))
        run["stages"] = {**report["seconds"], **report["solver"]["seconds"]}
        run["band_voxels"] = report["counts"]["band_voxels"]
        fuse_runs.append(run)
        shutil.rmtree(out, ignore_errors=True)
        o3d_out = tmp / f"o3d-{voxel}-{r}"
        o3d_runs.append(timed([sys.executable, __file__, "--open3d-child", str(data), str(voxel),
                               str(n), str(o3d_out)]))
        shutil.rmtree(o3d_out, ignore_errors=True)
        print(f"  {voxel * 100:g} cm run {r + 1}: fuse {fuse_runs[-1]['seconds']:.1f} s "
              f"({fuse_runs[-1]['peak_mib']:.0f} MiB), Open3D {o3d_runs[-1]['seconds']:.1f} s "
              f"({o3d_runs[-1]['peak_mib']:.0f} MiB)", flush=True)
    best_f = min(fuse_runs, key=lambda x: x["seconds"])
    best_o = min(o3d_runs, key=lambda x: x["seconds"])
    st = best_f["stages"]
    observe = st["observe"] + st.get("misfit", 0.0)
    ratios = {
        "observe/tsdf": observe / st["tsdf"],
        "map+variance/tsdf": (st["map"] + st.get("bias", 0.0) + st["variance"]) / st["tsdf"],
        "fuse/open3d": best_f["seconds"] / best_o["seconds"],
        "memory fuse/open3d": (min(r["peak_mib"] for r in fuse_runs)
                               / min(r["peak_mib"] for r in o3d_runs)),
    }
    return {"voxel": voxel, "frames": n, "fuse": best_f, "open3d": best_o, "ratios": ratios,
            "all_fuse_s": [r["seconds"] for r in fuse_runs],
            "all_open3d_s": [r["seconds"] for r in o3d_runs]}


def print_result(res: dict) -> None:
    st, f, o = res["fuse"]["stages"], res["fuse"], res["open3d"]
    print(f"\n## {res['voxel'] * 100:g} cm, {res['frames']} frames "
          f"(band {res['fuse']['band_voxels']:,} voxels)\n")
    print("| stage | seconds |\n|---|---|")
    keys = ["memory_check", "tsdf", "read_frames", "band", "noise", "observe", "prior", "map",
            "bias", "variance", "misfit", "mesh", "plots", "preview", "write", "total"]
    for k in keys:
        if k in st:
            print(f"| {k} | {st[k]:.2f} |")
    print(f"| whole `fuse` process | {f['seconds']:.2f} (peak {f['peak_mib']:.0f} MiB) |")
    print(f"| whole Open3D process | {o['seconds']:.2f} (peak {o['peak_mib']:.0f} MiB) |")
    print("\n| ratio | measured | target | met |\n|---|---|---|---|")
    for k, v in res["ratios"].items():
        print(f"| {k} | {v:.2f} | <= {TARGETS[k]:g} | {'yes' if v <= TARGETS[k] else 'no'} |")
    print(f"\nall runs: fuse {', '.join(f'{s:.1f}' for s in res['all_fuse_s'])} s; "
          f"Open3D {', '.join(f'{s:.1f}' for s in res['all_open3d_s'])} s")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--open3d-child":
        return open3d_child(Path(argv[1]), float(argv[2]), int(argv[3]), Path(argv[4]))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA), help="a 7-Scenes sequence folder")
    ap.add_argument("--voxels", default="0.02,0.01", help="comma-separated voxel sizes, metres")
    ap.add_argument("--frames", type=int, default=500, help="the first N frames")
    ap.add_argument("--repeats", type=int, default=2, help="alternating runs of each side")
    ap.add_argument("--json", help="also write the results here")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="a config override for `fuse` (repeatable), e.g. observation.model=voxels")
    args = ap.parse_args(argv)
    try:
        import open3d  # noqa: F401
    except ImportError:
        raise SystemExit("Open3D is not installed: pip install -e '.[compare]' (see README)")
    data = Path(args.data)
    if not (data / "camera-intrinsics.txt").is_file():
        raise SystemExit(f"{data}: not a 7-Scenes sequence (no camera-intrinsics.txt; see "
                         "../shared/data/README.md)")
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_pipeline_") as tmp:
        for voxel in (float(v) for v in args.voxels.split(",")):
            res = bench_voxel(data, voxel, args.frames, args.repeats, Path(tmp), tuple(args.set))
            results.append(res)
            print_result(res)
    if args.json:
        for r in results:
            r["fuse"].pop("stdout", None)
            r["open3d"].pop("stdout", None)
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
