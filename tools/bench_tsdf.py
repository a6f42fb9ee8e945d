#!/usr/bin/env python
"""TSDF integration speed: bftaichi's sparse Taichi kernel vs Open3D's tensor VoxelBlockGrid.

Integrates the 500 frames of ``../shared/data/rgbd/7scenes-redkitchen`` (640x480 Kinect depth)
at each voxel size and prints frames per second for both, their ratio, and how well the two
meshes agree::

    python tools/bench_tsdf.py                          # 2 cm and 1 cm, 500 frames, 3 repeats
    python tools/bench_tsdf.py --voxels 0.02 --frames 100 --repeats 1 --json out.json

Fair comparison, same run, same preloaded frames:
* truncation ``trunc_voxels`` (4) voxels for both (Open3D ``trunc_voxel_multiplier=4``);
  depth scale 1000, ``depth_max`` 6 m for both (our depth is cut at depth_max when loading).
* block activation from every 4th pixel in u and v for both (Open3D's
  ``compute_unique_block_coordinates`` uses a fixed stride of 4; we pass
  ``activation_stride=4``); blocks of 8^3 voxels; CPU. Open3D keeps tsdf and weight in float32;
  bftaichi keeps integer sums (int64 fixed-point sum, int32 count: exactly subtractable).
* only integration is timed (frames preloaded: float32 metres for us, ``o3d.t.geometry.Image``
  uint16 for Open3D; per frame Open3D runs compute_unique_block_coordinates + integrate). Taichi
  kernels are compiled before timing (the compile cost is reported separately, below).
* the machine may be shared and noisy: both systems run interleaved, ``--repeats`` times each,
  and the best run of each is reported (all runs are printed too).

Mesh agreement (needs Open3D): ``bftaichi.stages.surface.extract_mesh`` on our export over cells whose
corners have weight >= ``--weight-ours`` (1) against Open3D's ``extract_triangle_mesh()`` with
its default weight threshold (``--weight-o3d``, 3); a second line compares both at the same
threshold, so that both meshes cover the same voxels. Chamfer distance = mean d^2 both ways
(m^2), d = distance from each of ``--mesh-samples`` area-weighted trimesh samples of one mesh to
the other mesh's surface (exact point-to-triangle, Open3D RaycastingScene). The
sample-to-nearest-sample version (scipy cKDTree) is printed too; it adds the sample spacing to
every distance.

JIT overhead: the bftaichi part (4 frames and 2 exports) runs twice more in subprocesses that
share a fresh, empty Taichi offline cache (``TI_OFFLINE_CACHE_FILE_PATH``): *cold* = the extra
time of the first integrate and the first export when every kernel is compiled, *warm* = the
same with the cache the cold run filled (Taichi still parses the kernels to find them there).
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

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DEFAULT_DATA = ROOT / ".." / "shared" / "data" / "rgbd" / "7scenes-redkitchen"
DEPTH_SCALE = 1000.0  # 7-Scenes depth PNGs are millimetres
INVALID_RAW = 65535  # 7-Scenes "no measurement" code (besides 0)


# -- data ------------------------------------------------------------------------------------

def load_frames(data: Path, n: int, depth_max: float):
    """K (3,3), raw depth list (H,W) uint16 (for Open3D), depth list (H,W) float32 metres with
    invalid / beyond-depth_max pixels 0 (for us), poses T_W_C (4,4) float64."""
    from PIL import Image

    K = np.loadtxt(data / "camera-intrinsics.txt").reshape(3, 3)
    names = sorted(p.name[: -len(".depth.png")] for p in data.glob("frame-*.depth.png"))[:n]
    if not names:
        raise SystemExit(f"{data}: no frame-*.depth.png files (see ../shared/data/README.md)")
    raws, depths, poses = [], [], []
    for name in names:
        with Image.open(data / f"{name}.depth.png") as im:
            raw = np.array(im).astype(np.uint16)
        raw[raw == INVALID_RAW] = 0
        depth = raw.astype(np.float32) / np.float32(DEPTH_SCALE)
        depth[depth > depth_max] = 0
        raws.append(raw)
        depths.append(np.ascontiguousarray(depth))
        poses.append(np.loadtxt(data / f"{name}.pose.txt").reshape(4, 4))
    return K, raws, depths, poses


# -- the two integrators ---------------------------------------------------------------------

def run_bftaichi(depths, K, poses, voxel, trunc, stride):
    """Integrate all frames into a fresh volume; return (seconds, volume, voxel updates)."""
    import taichi as ti
    from kernels.tsdf import SparseTSDF

    vol = SparseTSDF(voxel, trunc)
    ti.sync()
    updates = 0
    t0 = time.perf_counter()
    for depth, T in zip(depths, poses):
        updates += vol.integrate(depth, K, T, activation_stride=stride)
    ti.sync()
    return time.perf_counter() - t0, vol, updates


class Open3DRunner:
    """Open3D tensor VoxelBlockGrid on CPU:0 with the frames preloaded as Open3D types."""

    def __init__(self, raws, K, poses):
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.images = [o3d.t.geometry.Image(o3c.Tensor(r)) for r in raws]
        self.extrinsics = [o3c.Tensor(np.linalg.inv(T), o3c.float64) for T in poses]
        self.intrinsic = o3c.Tensor(K, o3c.float64)

    def run(self, voxel, trunc_voxels, depth_max, block_count):
        o3d, o3c = self.o3d, self.o3c
        vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)), voxel_size=voxel, block_resolution=8,
            block_count=block_count, device=o3c.Device("CPU:0"))
        t0 = time.perf_counter()
        for depth, ext in zip(self.images, self.extrinsics):
            blocks = vbg.compute_unique_block_coordinates(
                depth, self.intrinsic, ext, DEPTH_SCALE, depth_max, trunc_voxels)
            vbg.integrate(blocks, depth, self.intrinsic, ext, DEPTH_SCALE, depth_max,
                          trunc_voxels)
        return time.perf_counter() - t0, vbg


# -- mesh agreement --------------------------------------------------------------------------

def surface_distances(points: np.ndarray, mesh) -> np.ndarray:
    """Exact distance (m) from each point (N, 3) to the triangle mesh ``mesh`` (trimesh), by
    Open3D's RaycastingScene (point-to-triangle, not point-to-sample)."""
    import open3d as o3d
    import open3d.core as o3c

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3c.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene.compute_distance(o3c.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def chamfer(mesh_a, mesh_b, n_samples: int, seed: int = 0) -> dict:
    """Symmetric Chamfer distance (m^2) between two trimesh meshes: ``n_samples`` area-weighted
    surface samples of each (trimesh, fixed seeds), mean squared distance to the other mesh,
    summed over both directions.

    ``chamfer_m2`` measures the distance from each sample to the other *surface* (exact);
    ``chamfer_samples_m2`` to the other mesh's nearest *sample* (scipy cKDTree), which adds the
    sample spacing (~sqrt(area / n_samples)) to every distance and so overstates the gap."""
    import trimesh
    from scipy.spatial import cKDTree

    pa, _ = trimesh.sample.sample_surface(mesh_a, n_samples, seed=seed)
    pb, _ = trimesh.sample.sample_surface(mesh_b, n_samples, seed=seed + 1)
    d_ab, d_ba = surface_distances(pa, mesh_b), surface_distances(pb, mesh_a)
    s_ab, _ = cKDTree(pb).query(pa, workers=-1)
    s_ba, _ = cKDTree(pa).query(pb, workers=-1)
    return {"chamfer_m2": float(np.mean(d_ab ** 2) + np.mean(d_ba ** 2)),
            "chamfer_samples_m2": float(np.mean(s_ab ** 2) + np.mean(s_ba ** 2)),
            "median_dist_ours_to_o3d_m": float(np.median(d_ab)),
            "median_dist_o3d_to_ours_m": float(np.median(d_ba)),
            "p99_dist_ours_to_o3d_m": float(np.percentile(d_ab, 99)),
            "p99_dist_o3d_to_ours_m": float(np.percentile(d_ba, 99))}


def mesh_agreement(vol, vbg, voxel, w_ours, w_o3d, n_samples) -> dict:
    """Compare ``bftaichi.stages.surface.extract_mesh`` on our export (cells whose 8 corners have
    weight >= ``w_ours``) with Open3D's ``extract_triangle_mesh(weight_threshold=w_o3d)``."""
    import trimesh
    from bftaichi.stages.surface import extract_mesh

    ex = vol.export()
    t0 = time.perf_counter()
    v, f = extract_mesh(ex["ijk"], ex["tsdf"], ex["weight"] >= w_ours, voxel)
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    m = vbg.extract_triangle_mesh(weight_threshold=w_o3d)
    t_o3d = time.perf_counter() - t0
    ours = trimesh.Trimesh(v, f, process=False)
    theirs = trimesh.Trimesh(m.vertex.positions.numpy(), m.triangle.indices.numpy(),
                             process=False)
    out = chamfer(ours, theirs, n_samples)
    out.update(voxel_m=voxel, weight_ours=w_ours, weight_o3d=w_o3d,
               chamfer_over_voxel2=out["chamfer_m2"] / voxel ** 2,
               faces_ours=int(len(f)), faces_o3d=int(len(theirs.faces)),
               area_ours_m2=float(ours.area), area_o3d_m2=float(theirs.area),
               extract_s_ours=t_ours, extract_s_o3d=t_o3d)
    return out


# -- JIT overhead (subprocess) ---------------------------------------------------------------

def jit_child(args) -> int:
    """Run in a subprocess: time Taichi start-up, the first frames and two exports; print one
    JSON line. The first integrate and the first export include compiling (or loading from the
    offline cache) their kernels; the later ones are the steady-state reference."""
    K, _, depths, poses = load_frames(Path(args.data), 4, args.depth_max)
    t0 = time.perf_counter()
    from bftaichi.backend import init
    import kernels.tsdf  # noqa: F401
    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    init("cpu")
    t_init = time.perf_counter() - t0
    from kernels.tsdf import SparseTSDF

    voxel = args.voxels[0]
    vol = SparseTSDF(voxel, args.trunc_voxels * voxel)
    frame_s, export_s = [], []
    for i, (depth, T) in enumerate(zip(depths, poses)):
        t0 = time.perf_counter()
        vol.integrate(depth, K, T, activation_stride=args.stride)
        frame_s.append(time.perf_counter() - t0)
        if i in (0, len(depths) - 1):
            t0 = time.perf_counter()
            vol.export()
            export_s.append(time.perf_counter() - t0)
    print(json.dumps({"import_s": t_import, "init_s": t_init, "frame_s": frame_s,
                      "export_s": export_s}))
    return 0


def jit_overhead(args) -> dict:
    cache = tempfile.mkdtemp(prefix="ti-cache-bench-")
    env = dict(os.environ, TI_OFFLINE_CACHE_FILE_PATH=cache)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--jit-child", "--data", str(args.data),
           "--voxels", str(args.voxels[0]), "--depth-max", str(args.depth_max),
           "--trunc-voxels", str(args.trunc_voxels), "--stride", str(args.stride)]
    out = {}
    try:
        for label in ("cold", "warm"):
            t0 = time.perf_counter()
            res = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=str(ROOT))
            wall = time.perf_counter() - t0
            if res.returncode != 0:
                raise SystemExit(f"JIT subprocess failed:\n{res.stderr}")
            r = json.loads(res.stdout.strip().splitlines()[-1])
            steady = float(np.median(r["frame_s"][1:]))
            out[label] = {"process_wall_s": wall, "import_s": r["import_s"], "init_s": r["init_s"],
                          "first_frame_s": r["frame_s"][0], "steady_frame_s": steady,
                          "first_export_s": r["export_s"][0], "steady_export_s": r["export_s"][1],
                          "overhead_s": (r["frame_s"][0] - steady
                                         + r["export_s"][0] - r["export_s"][1])}
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return out


# -- main ------------------------------------------------------------------------------------

def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="7-Scenes sequence folder")
    ap.add_argument("--voxels", type=float, nargs="+", default=[0.02, 0.01],
                    help="voxel sizes, metres (default 0.02 0.01)")
    ap.add_argument("--frames", type=int, default=500, help="frames to integrate (default 500)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per system (best kept)")
    ap.add_argument("--trunc-voxels", type=float, default=4.0, help="truncation in voxels")
    ap.add_argument("--depth-max", type=float, default=6.0, help="metres (both systems)")
    ap.add_argument("--stride", type=int, default=4,
                    help="activation pixel stride (Open3D's is fixed at 4)")
    ap.add_argument("--weight-ours", type=float, default=1.0,
                    help="our mesh: cells whose 8 corners have weight >= this (default 1)")
    ap.add_argument("--weight-o3d", type=float, default=3.0,
                    help="Open3D's extract_triangle_mesh weight_threshold (its default 3)")
    ap.add_argument("--mesh-samples", type=int, default=200_000)
    ap.add_argument("--no-open3d", action="store_true", help="skip Open3D even if installed")
    ap.add_argument("--no-mesh", action="store_true", help="skip the mesh comparison")
    ap.add_argument("--no-jit", action="store_true", help="skip the cold/warm JIT measurement")
    ap.add_argument("--json", type=Path, help="also write all numbers to this JSON file")
    ap.add_argument("--jit-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.frames < 3 or args.repeats < 1 or args.stride < 1 or args.mesh_samples < 1000:
        ap.error("need --frames >= 3, --repeats >= 1, --stride >= 1, --mesh-samples >= 1000")
    if any(not (0.001 <= v <= 0.5) for v in args.voxels):
        ap.error("--voxels must be in [0.001, 0.5] m")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.jit_child:
        return jit_child(args)
    if not (args.data / "camera-intrinsics.txt").is_file():
        raise SystemExit(f"{args.data}: not a 7-Scenes folder (no camera-intrinsics.txt)")

    t_start = time.perf_counter()
    t0 = time.perf_counter()
    K, raws, depths, poses = load_frames(args.data, args.frames, args.depth_max)
    n = len(depths)
    print(f"data: {args.data.resolve()}  {n} frames {depths[0].shape[1]}x{depths[0].shape[0]}, "
          f"loaded in {time.perf_counter() - t0:.1f} s")

    o3d_runner = None
    if args.no_open3d:
        o3d_note = "Open3D skipped (--no-open3d): bftaichi numbers only"
    else:
        try:
            import open3d
            o3d_runner = Open3DRunner(raws, K, poses)
            o3d_note = f"Open3D {open3d.__version__} (tensor VoxelBlockGrid, CPU:0)"
        except ImportError:
            o3d_note = "Open3D is not installed: bftaichi numbers only (pip install open3d)"
    print(o3d_note)

    import taichi as ti
    from bftaichi.backend import init

    init("cpu")
    from kernels.tsdf import SparseTSDF

    # Compile every kernel before timing (measured separately in the JIT section).
    t0 = time.perf_counter()
    warm = SparseTSDF(args.voxels[0], args.trunc_voxels * args.voxels[0])
    for depth, T in zip(depths[:2], poses[:2]):
        warm.integrate(depth, K, T, activation_stride=args.stride)
    warm.export()
    del warm
    print(f"Taichi warm-up (compile or offline-cache load): {time.perf_counter() - t0:.2f} s; "
          f"CPU threads: {ti.lang.impl.current_cfg().cpu_max_num_threads}")

    runs = {v: {"ours_s": [], "o3d_s": []} for v in args.voxels}
    last = {}
    for rep in range(args.repeats):
        for voxel in args.voxels:
            r = runs[voxel]
            sec, vol, updates = run_bftaichi(depths, K, poses, voxel, args.trunc_voxels * voxel,
                                             args.stride)
            r["ours_s"].append(sec)
            r["updates_per_frame"] = updates / n
            r["blocks_ours"] = vol.stats()["blocks"]
            line = (f"  run {rep + 1}/{args.repeats}  {voxel * 100:g} cm:  bftaichi "
                    f"{n / sec:6.1f} frames/s")
            vbg = None
            if o3d_runner is not None:
                block_count = max(50_000, 2 * r["blocks_ours"])
                sec_o, vbg = o3d_runner.run(voxel, args.trunc_voxels, args.depth_max, block_count)
                r["o3d_s"].append(sec_o)
                r["blocks_o3d"] = int(vbg.hashmap().size())
                line += f"   Open3D {n / sec_o:6.1f} frames/s"
            print(line, flush=True)
            last[voxel] = (vol, vbg)
            del vol, vbg

    report = {"frames": n, "repeats": args.repeats, "trunc_voxels": args.trunc_voxels,
              "depth_max_m": args.depth_max, "activation_stride": args.stride,
              "open3d": o3d_note, "voxels": {}}
    for voxel in args.voxels:
        r = runs[voxel]
        e = {"fps_ours_best": n / min(r["ours_s"]), "fps_ours_all": [n / s for s in r["ours_s"]],
             "blocks_ours": r["blocks_ours"], "updates_per_frame": r["updates_per_frame"]}
        if r["o3d_s"]:
            e.update(fps_o3d_best=n / min(r["o3d_s"]), fps_o3d_all=[n / s for s in r["o3d_s"]],
                     blocks_o3d=r["blocks_o3d"], ratio_best=min(r["o3d_s"]) / min(r["ours_s"]))
        report["voxels"][str(voxel)] = e

    if not args.no_mesh and o3d_runner is not None:
        print("mesh agreement ...", flush=True)
        for voxel in args.voxels:
            vol, vbg = last[voxel]
            e = report["voxels"][str(voxel)]
            e["mesh"] = mesh_agreement(vol, vbg, voxel, args.weight_ours, args.weight_o3d,
                                       args.mesh_samples)
            if args.weight_ours != args.weight_o3d:
                e["mesh_same_weight"] = mesh_agreement(vol, vbg, voxel, args.weight_o3d,
                                                       args.weight_o3d, args.mesh_samples)
    last.clear()

    if not args.no_jit:
        print("JIT overhead (2 subprocesses sharing a new, empty Taichi offline cache) ...",
              flush=True)
        report["jit"] = jit_overhead(args)

    print_report(report, args)
    print(f"bench wall time: {time.perf_counter() - t_start:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.json}")
    return 0


def print_report(report: dict, args) -> None:
    n = report["frames"]
    print()
    print(f"TSDF integration, {n} frames of 7-Scenes redkitchen (640x480), trunc "
          f"{args.trunc_voxels:g} voxels, depth_max {args.depth_max:g} m, activation stride "
          f"{args.stride}, best of {args.repeats} runs; {report['open3d']}")
    head = (f"{'voxel':>5} | {'bftaichi frames/s':>17} | {'Open3D frames/s':>15} | {'ratio':>5} | "
            f"{'blocks ours/O3D':>15} | {'updates/frame':>13} | {'CD m^2':>9} | "
            f"{'CD/voxel^2':>10} | {'same-weight CD/voxel^2':>22}")
    print(head)
    print("-" * len(head))
    for voxel in args.voxels:
        e = report["voxels"][str(voxel)]
        cell = lambda key, fmt, w: format(e[key], fmt) if key in e else f"{'-':>{w}}"  # noqa: E731
        m, m2 = e.get("mesh"), e.get("mesh_same_weight", e.get("mesh"))
        print(f"{voxel * 100:3g}cm | {e['fps_ours_best']:17.1f} | {cell('fps_o3d_best', '15.1f', 15)}"
              f" | {cell('ratio_best', '5.2f', 5)} | "
              f"{str(e['blocks_ours']) + '/' + str(e.get('blocks_o3d', '-')):>15} | "
              f"{e['updates_per_frame']:13.0f} | "
              + (f"{m['chamfer_m2']:9.2e} | {m['chamfer_over_voxel2']:10.3f} | "
                 f"{m2['chamfer_over_voxel2']:22.3f}" if m else f"{'-':>9} | {'-':>10} | {'-':>22}"))
    print("ratio = bftaichi frames/s / Open3D frames/s (best runs). All runs (frames/s):")
    for voxel in args.voxels:
        e = report["voxels"][str(voxel)]
        line = f"  {voxel * 100:g} cm: bftaichi " + ", ".join(f"{x:.1f}" for x in e["fps_ours_all"])
        if "fps_o3d_all" in e:
            line += "; Open3D " + ", ".join(f"{x:.1f}" for x in e["fps_o3d_all"])
        print(line)
    for voxel in args.voxels:
        e = report["voxels"][str(voxel)]
        for key in ("mesh", "mesh_same_weight"):
            m = e.get(key)
            if m:
                print(f"mesh {voxel * 100:g} cm, ours weight >= {m['weight_ours']:g} vs Open3D "
                      f"weight_threshold {m['weight_o3d']:g}: faces {m['faces_ours']} / "
                      f"{m['faces_o3d']}, area {m['area_ours_m2']:.2f} / {m['area_o3d_m2']:.2f} m^2, "
                      f"distance ours->O3D median {m['median_dist_ours_to_o3d_m'] * 1e3:.2f} mm "
                      f"(p99 {m['p99_dist_ours_to_o3d_m'] * 1e3:.1f}), O3D->ours median "
                      f"{m['median_dist_o3d_to_ours_m'] * 1e3:.2f} mm "
                      f"(p99 {m['p99_dist_o3d_to_ours_m'] * 1e3:.1f}); CD {m['chamfer_m2']:.2e} m^2 "
                      f"(sample-to-sample cKDTree: {m['chamfer_samples_m2']:.2e})")
    if "jit" in report:
        for label in ("cold", "warm"):
            j = report["jit"][label]
            print(f"Taichi {label} ({'empty' if label == 'cold' else 'filled'} offline cache): "
                  f"JIT overhead {j['overhead_s']:.2f} s = first frame {j['first_frame_s']:.2f} s "
                  f"(then {j['steady_frame_s'] * 1e3:.1f} ms) + first export "
                  f"{j['first_export_s']:.2f} s (then {j['steady_export_s'] * 1e3:.1f} ms); "
                  f"ti.init {j['init_s']:.2f} s, import {j['import_s']:.2f} s, whole process "
                  f"{j['process_wall_s']:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
