#!/usr/bin/env python
"""Chunked against monolithic posterior solves (issue 20, item 3): is ``run.chunk_m`` right,
and how large a halo does it need?

Fuses the frames once, solves the whole band (monolithic), then solves it again in chunks of
``--chunk-m`` metres with each halo of ``--halos`` voxels (cold, no warm start), and prints per
halo: the number of chunks, max |mean difference| over the observed band voxels (voxels), the
median |sigma difference| / sigma, the Chamfer distance between the two meshes (exact
point-to-mesh distances of ``--samples`` area samples each way, mean of d^2, in voxel^2), the
seconds of each solve, and, for a scene with ground truth, the vertex calibration of both
meshes (coverage at 1 / 2 / 3 sigma, NLL minus the best constant's)::

    python tools/chunk_table.py                             # 500 redkitchen frames, 2 cm
    python tools/chunk_table.py --frames 100 --halos 4 8 --chunk-m 1.5
    python tools/chunk_table.py --scene scenes/bunny.toml --chunk-m 0.1 --set tsdf.voxel_size_m=0.004

Issue 20's bounds: max |dmean| < 0.1 voxel, median |dsigma| / sigma < 5 %, Chamfer < 0.05
voxel^2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DEFAULT_DATA = ROOT / ".." / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def chamfer(a, b, n: int, seed: int = 0) -> float:
    """Mean squared exact distance of ``n`` area samples of each mesh to the other, both ways."""
    from bftaichi.evaluation.metrics import vertex_errors

    out = []
    for x, y in ((a, b), (b, a)):
        pts, _ = __import__("trimesh").sample.sample_surface(x, n, seed=seed)
        out.append(np.mean(vertex_errors(np.asarray(pts), y) ** 2))
    return float(np.mean(out))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="a dataset folder")
    ap.add_argument("--scene", type=Path, help="a scene file instead (synthetic: has ground truth)")
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--chunk-m", type=float, default=2.0)
    ap.add_argument("--halos", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--samples", type=int, default=100_000)
    ap.add_argument("--set", dest="sets", action="append", default=[])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.evaluation.metrics import vertex_uncertainty
    from bftaichi.running.pipeline import load_gt_mesh, open_frames

    bf.init("cpu")
    if args.scene:
        cfg = bf.load_config(args.scene, args.sets)
        frames = open_frames(cfg)
        gt = load_gt_mesh(cfg, frames)
    else:
        cfg = bf.load_config(None, [f"tsdf.voxel_size_m={args.voxel}",
                                    f"tsdf.trunc_m={2 * args.voxel}", *args.sets])
        frames = bf.open_dataset(args.data, depth_min_m=cfg.scene.depth_min_m,
                                 depth_max_m=cfg.scene.depth_max_m,
                                 frames=slice(0, args.frames))
        gt = None
    vs = cfg.tsdf.voxel_size_m
    recon = bf.Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    print(f"{len(recon.frames)} frames of {getattr(frames, 'name', args.scene)}, "
          f"{vs * 100:g} cm voxels, chunks of {args.chunk_m:g} m")

    def solve(chunk_m: float, halo: int):
        recon.config = dataclasses.replace(cfg, run=dataclasses.replace(
            cfg.run, chunk_m=chunk_m, chunk_halo=halo))
        recon.posterior = None  # cold, as the monolithic solve
        t0 = time.perf_counter()
        post = recon.solve()
        return post, time.perf_counter() - t0

    mono, t_mono = solve(0.0, 1)
    mono_mesh = mono.extract_mesh()
    rows = []
    cal = (lambda m: vertex_uncertainty(m, gt)) if gt is not None else (lambda m: None)
    mono_cal = cal(mono_mesh)
    print(f"monolithic: band {len(mono.ijk):,} voxels, {t_mono:.1f} s, MAP "
          f"{mono.solver['iterations']} iterations")
    seen = mono.weight > 0
    s0 = np.sqrt(mono.var[seen])
    for halo in args.halos:
        post, t = solve(args.chunk_m, halo)
        assert np.array_equal(post.ijk, mono.ijk)
        dm = float(np.abs(post.mean - mono.mean)[seen].max() / vs)
        ds = float(np.median(np.abs(np.sqrt(post.var[seen]) - s0) / s0))
        mesh = post.extract_mesh()
        cd = chamfer(mesh, mono_mesh, args.samples) / vs ** 2
        c = post.solver["chunks"]
        row = {"halo": halo, "chunks": c["n"], "side_voxels": c["side_voxels"],
               "max_dmean_voxel": dm, "median_dsigma_rel": ds, "chamfer_voxel2": cd,
               "seconds": t, "seconds_monolithic": t_mono, "converged": post.solver["converged"],
               "calibration": cal(mesh), "stage_seconds": post.seconds,
               "per_chunk": c.get("per_chunk")}
        rows.append(row)
        print(f"halo {halo}: {c['n']} chunks of {c['side_voxels']} voxels, max |dmean| "
              f"{dm:.4f} voxel, median |dsigma|/sigma {100 * ds:.2f} %, Chamfer {cd:.2e} "
              f"voxel^2, {t:.1f} s (monolithic {t_mono:.1f} s), converged "
              f"{post.solver['converged']}", flush=True)
    for name, u in [("monolithic", mono_cal)] + [(f"halo {r['halo']}", r["calibration"])
                                                  for r in rows]:
        if u:
            print(f"vertex calibration, {name}: coverage 1/2/3 sigma "
                  f"{100 * u['coverage@1sigma']:.1f} / {100 * u['coverage@2sigma']:.1f} / "
                  f"{100 * u['coverage@3sigma']:.1f} %, NLL - const {u['nll_vs_constant']:+.3f}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "monolithic_calibration": mono_cal,
                                         "seconds_monolithic": t_mono,
                                         "stage_seconds_monolithic": mono.seconds,
                                         "band_voxels": len(mono.ijk),
                                         "frames": len(recon.frames), "voxel_size_m": vs,
                                         "chunk_m": args.chunk_m},
                                        indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
