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
  ``activation_stride=4``); blocks of 8^3 voxels; tsdf and weight float32; CPU.
* only integration is timed (frames preloaded: float32 metres for us, ``o3d.t.geometry.Image``
  uint16 for Open3D; per frame Open3D runs compute_unique_block_coordinates + integrate). Taichi
  kernels are compiled before timing (the compile cost is reported separately, below).
* the machine may be shared and noisy: both systems run interleaved, ``--repeats`` times each,
  and the best run of each is reported (all runs are printed too).

Mesh agreement: Open3D's ``extract_triangle_mesh()`` (its default weight threshold 3) against
``bftaichi.meshing.extract_mesh`` on our export with the same threshold (weight >= 3, so both
meshes cover the same voxels; ``--min-weight`` changes it). Chamfer distance = mean d^2 both ways
(m^2) between ``--mesh-samples`` area-weighted surface samples of each mesh (fixed seed).

JIT overhead: the bftaichi part runs twice more in a subprocess with a fresh, empty Taichi
offline cache (``TI_OFFLINE_CACHE_FILE_PATH``): *cold* = the first frame's extra time when every
kernel is compiled, *warm* = the same with the cache the cold run filled.
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
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

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

def chamfer(mesh_a, mesh_b, n_samples: int, seed: int = 0) -> dict:
    """Symmetric Chamfer distance between two trimesh meshes: mean squared nearest-neighbour
    distance of ``n_samples`` area-weighted surface samples, both ways (m^2), and the mean
    (unsquared) distances."""
    import trimesh
    from scipy.spatial import cKDTree

    pa, _ = trimesh.sample.sample_surface(mesh_a, n_samples, seed=seed)
    pb, _ = trimesh.sample.sample_surface(mesh_b, n_samples, seed=seed + 1)
    d_ab, _ = cKDTree(pb).query(pa, workers=-1)
    d_ba, _ = cKDTree(pa).query(pb, workers=-1)
    return {"chamfer_m2": float(np.mean(d_ab ** 2) + np.mean(d_ba ** 2)),
            "mean_dist_ours_to_o3d_m": float(d_ab.mean()),
            "mean_dist_o3d_to_ours_m": float(d_ba.mean())}


def mesh_agreement(vol, vbg, voxel, min_weight, n_samples) -> dict:
    import trimesh
    from bftaichi.meshing import extract_mesh

    t0 = time.perf_counter()
    ex = vol.export()
    v, f = extract_mesh(ex["ijk"], ex["tsdf"], ex["weight"] >= min_weight, voxel)
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    m = vbg.extract_triangle_mesh(weight_threshold=min_weight)
    t_o3d = time.perf_counter() - t0
    ours = trimesh.Trimesh(v, f, process=False)
    theirs = trimesh.Trimesh(m.vertex.positions.numpy(), m.triangle.indices.numpy(),
                             process=False)
    out = chamfer(ours, theirs, n_samples)
    out.update(voxel_m=voxel, min_weight=min_weight, chamfer_over_voxel2=out["chamfer_m2"] / voxel ** 2,
               faces_ours=int(len(f)), faces_o3d=int(len(theirs.faces)),
               area_ours_m2=float(ours.area), area_o3d_m2=float(theirs.area),
               extract_s_ours=t_ours, extract_s_o3d=t_o3d)
    return out


# -- JIT overhead (subprocess) ---------------------------------------------------------------

def jit_child(args) -> int:
    """Run in a subprocess: time Taichi start-up and the first frames; print one JSON line."""
    t0 = time.perf_counter()
    K, _, depths, poses = load_frames(Path(args.data), 3, args.depth_max)
    t_load = time.perf_counter() - t0
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
    times = []
    for depth, T in zip(depths, poses):
        t0 = time.perf_counter()
        vol.integrate(depth, K, T, activation_stride=args.stride)
        vol.export() if len(times) == 0 else None  # the export path is compiled once too
        times.append(time.perf_counter() - t0)
    print(json.dumps({"load_s": t_load, "import_s": t_import, "init_s": t_init,
                      "frame_s": times}))
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
                          "overhead_s": r["frame_s"][0] - steady}
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return out


# -- main ------------------------------------------------------------------------------------

def main(argv=None) -> int:
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
    ap.add_argument("--min-weight", type=float, default=3.0,
                    help="mesh weight threshold for both (Open3D's default is 3)")
    ap.add_argument("--mesh-samples", type=int, default=200_000)
    ap.add_argument("--no-open3d", action="store_true", help="skip Open3D even if installed")
    ap.add_argument("--no-mesh", action="store_true", help="skip the mesh comparison")
    ap.add_argument("--no-jit", action="store_true", help="skip the cold/warm JIT measurement")
    ap.add_argument("--json", type=Path, help="also write all numbers to this JSON file")
    ap.add_argument("--jit-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
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
    o3d_note = ""
    if not args.no_open3d:
        try:
            import open3d
            o3d_runner = Open3DRunner(raws, K, poses)
            o3d_note = f"Open3D {open3d.__version__}"
        except ImportError:
            o3d_note = "Open3D is not installed: bftaichi numbers only (pip install open3d)"
    else:
        o3d_note = "Open3D skipped (--no-open3d)"
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
    print(f"Taichi warm-up (compile or offline-cache load): {time.perf_counter() - t0:.2f} s; "
          f"threads: {ti.lang.impl.current_cfg().cpu_max_num_threads}")

    results = {v: {"ours_s": [], "o3d_s": []} for v in args.voxels}
    last = {}
    for rep in range(args.repeats):
        for voxel in args.voxels:
            trunc = args.trunc_voxels * voxel
            r = results[voxel]
            sec, vol, updates = run_bftaichi(depths, K, poses, voxel, trunc, args.stride)
            r["ours_s"].append(sec)
            r["updates_per_frame"] = updates / n
            r["blocks_ours"] = vol.stats()["blocks"]
            line = f"  run {rep + 1}/{args.repeats} voxel {voxel * 100:g} cm: bftaichi {n / sec:7.1f} fps"
            vbg = None
            if o3d_runner is not None:
                block_count = max(50_000, 2 * r["blocks_ours"])
                sec_o, vbg = o3d_runner.run(voxel, args.trunc_voxels, args.depth_max, block_count)
                r["o3d_s"].append(sec_o)
                r["blocks_o3d"] = int(vbg.hashmap().size())
                line += f"   Open3D {n / sec_o:7.1f} fps"
            print(line, flush=True)
            if rep == args.repeats - 1:
                last[voxel] = (vol, vbg)
            else:
                del vol, vbg

    report = {"frames": n, "repeats": args.repeats, "trunc_voxels": args.trunc_voxels,
              "depth_max_m": args.depth_max, "activation_stride": args.stride,
              "open3d": o3d_note, "voxels": {}}
    for voxel in args.voxels:
        r = results[voxel]
        entry = {"fps_ours_best": n / min(r["ours_s"]), "fps_ours_all": [n / s for s in r["ours_s"]],
                 "blocks_ours": r["blocks_ours"], "updates_per_frame": r["updates_per_frame"]}
        if r["o3d_s"]:
            entry.update(fps_o3d_best=n / min(r["o3d_s"]), fps_o3d_all=[n / s for s in r["o3d_s"]],
                         blocks_o3d=r["blocks_o3d"],
                         ratio_best=min(r["o3d_s"]) / min(r["ours_s"]))
        report["voxels"][str(voxel)] = entry

    if not args.no_mesh and o3d_runner is not None:
        print("mesh agreement ...", flush=True)
        for voxel in args.voxels:
            vol, vbg = last[voxel]
            report["voxels"][str(voxel)]["mesh"] = mesh_agreement(
                vol, vbg, voxel, args.min_weight, args.mesh_samples)
    last.clear()

    if not args.no_jit:
        print("JIT overhead (subprocesses with an empty Taichi offline cache) ...", flush=True)
        report["jit"] = jit_overhead(args)

    # -- table -----------------------------------------------------------------------------
    print()
    print(f"TSDF integration, {n} frames of 7-Scenes redkitchen, trunc {args.trunc_voxels:g} voxels, "
          f"depth_max {args.depth_max:g} m, activation stride {args.stride}, best of {args.repeats}")
    head = f"{'voxel':>6} | {'bftaichi fps':>12} | {'Open3D fps':>10} | {'ratio':>5} | " \
           f"{'blocks ours/O3D':>15} | {'upd/frame':>9} | {'Chamfer m^2':>11} | {'CD/voxel^2':>10}"
    print(head)
    print("-" * len(head))
    for voxel in args.voxels:
        e = report["voxels"][str(voxel)]
        o3d_fps = f"{e['fps_o3d_best']:10.1f}" if "fps_o3d_best" in e else f"{'-':>10}"
        ratio = f"{e['ratio_best']:5.2f}" if "ratio_best" in e else f"{'-':>5}"
        blocks = f"{e['blocks_ours']}/{e.get('blocks_o3d', '-')}"
        cd = f"{e['mesh']['chamfer_m2']:11.3e}" if "mesh" in e else f"{'-':>11}"
        cdv = f"{e['mesh']['chamfer_over_voxel2']:10.3f}" if "mesh" in e else f"{'-':>10}"
        print(f"{voxel * 100:4g}cm | {e['fps_ours_best']:12.1f} | {o3d_fps} | {ratio} | "
              f"{blocks:>15} | {e['updates_per_frame']:9.0f} | {cd} | {cdv}")
    print("(ratio = bftaichi fps / Open3D fps; all runs: "
          + "; ".join(f"{v * 100:g} cm ours " + ", ".join(f"{x:.0f}" for x in report["voxels"][str(v)]["fps_ours_all"])
                      + (" / O3D " + ", ".join(f"{x:.0f}" for x in report["voxels"][str(v)]["fps_o3d_all"])
                         if "fps_o3d_all" in report["voxels"][str(v)] else "")
                      for v in args.voxels) + ")")
    for voxel in args.voxels:
        m = report["voxels"][str(voxel)].get("mesh")
        if m:
            print(f"mesh {voxel * 100:g} cm (weight >= {m['min_weight']:g}): faces ours {m['faces_ours']} / "
                  f"O3D {m['faces_o3d']}, area {m['area_ours_m2']:.2f} / {m['area_o3d_m2']:.2f} m^2, "
                  f"mean dist ours->O3D {m['mean_dist_ours_to_o3d_m'] * 1000:.2f} mm, "
                  f"O3D->ours {m['mean_dist_o3d_to_ours_m'] * 1000:.2f} mm")
    if "jit" in report:
        for label in ("cold", "warm"):
            j = report["jit"][label]
            print(f"Taichi {label:4s} ({'empty' if label == 'cold' else 'filled'} offline cache): "
                  f"first-frame overhead {j['overhead_s']:.2f} s (first {j['first_frame_s']:.2f} s, "
                  f"steady {j['steady_frame_s'] * 1000:.1f} ms), ti.init {j['init_s']:.2f} s, "
                  f"process {j['process_wall_s']:.1f} s")
    print(f"bench wall time: {time.perf_counter() - t_start:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
