"""Where the rays model's observation pass spends a real frame (issue 16; measured, not built:
docs/measurements.md, "Where the observation pass spends a frame").

    python docs/experiments/observation_profile.py                 # redkitchen, 2 cm
    python docs/experiments/observation_profile.py --voxel 0.01 --timed 10

Fuses the frames into the TSDF and builds the posterior's band, as ``tools/bench_observe.py``
does, then prints, over ``--timed`` frames spread over the sequence (frames preloaded, kernels
compiled first, the calls interleaved frame by frame):

1. the rays a frame casts per level of its super-pixel pyramid (``observation.aggregate``) and
   the pixels each level covers;
2. milliseconds per frame (median) of ``Observer.integrate`` (the data term: 36 + 8 fixed-point
   adds per accepted sample), ``Observer.information`` (its diagonal only: 8 adds, the same
   samples, lookups and normals) and ``Observer.misfit`` (the local-noise pass: the samples
   within 1.5 voxels of their pixel's surface, against a field ``mu``, ``var``);
3. ``Observer.integrate`` with the band's voxels in lexicographic order (the band's) against
   the same voxels numbered block by block (8^3 blocks, so that a cell's corners and a ray's
   next cells lie close in the accumulators), and that both give the same sums.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA))
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--timed", type=int, default=30)
    args = ap.parse_args()

    import bftaichi as bf
    from bftaichi.frame import local_frames
    from bftaichi.stages.band import Band, build_band
    from bftaichi.stages.observe import make_observer

    vox = args.voxel
    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={vox}", f"tsdf.trunc_m={2 * vox}"])
    recon = bf.Reconstructor(cfg)
    for f in bf.open_dataset(args.data, frames=slice(0, args.frames)):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, x0 = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)
    picks = np.unique(np.linspace(0, len(frames) - 1, args.timed).round().astype(int))
    obs = make_observer(band, cfg.observation, vox, cfg.tsdf.trunc_m)

    # 1. rays per pyramid level
    rays, covered = {}, {}
    for i in picks:
        f = frames[int(i)]
        depth, prm = obs._frame_params(f.depth_m, f.K, f.T_W_C, None)
        for _, mask, _, k in obs._levels(depth, prm, 1):
            n = int(np.count_nonzero(mask == 1))
            rays[k] = rays.get(k, 0) + n / len(picks)
            covered[k] = covered.get(k, 0) + k * k * n / len(picks)
    total_rays, total_px = sum(rays.values()), sum(covered.values())
    print(f"{vox * 100:g} cm, band {len(band):,} voxels, {len(picks)} frames")
    print("| block side k | rays per frame | share of the rays | pixels covered | share of the "
          "pixels |\n|---|---|---|---|---|")
    for k in sorted(rays, reverse=True):
        print(f"| {k} | {rays[k]:,.0f} | {100 * rays[k] / total_rays:.1f} % | {covered[k]:,.0f} | "
              f"{100 * covered[k] / total_px:.1f} % |")

    # 2. and 3.: the block-major numbering of the same band
    rows, t = np.nonzero(band.block_table >= 0)
    perm = band.block_table[rows, t].astype(np.int64)  # new index q holds old index perm[q]
    rank = np.empty(len(band), np.int32)
    rank[perm] = np.arange(len(band), dtype=np.int32)
    table = np.where(band.block_table >= 0, rank[np.maximum(band.block_table, 0)], -1)
    blocked = Band(ijk=band.ijk[perm], tsdf=band.tsdf[perm], weight=band.weight[perm],
                   block_keys=band.block_keys, block_table=table.astype(np.int32))
    obs_b = make_observer(blocked, cfg.observation, vox, cfg.tsdf.trunc_m)
    mu, var = x0.astype(np.float32), np.full(len(band), (0.1 * vox) ** 2, np.float32)
    calls = {
        "integrate": lambda f: obs.integrate(f.depth_m, f.K, f.T_W_C),
        "information": lambda f: obs.information(f.depth_m, f.K, f.T_W_C),
        "misfit": lambda f: obs.misfit(f.depth_m, f.K, f.T_W_C, mu, var),
        "integrate, block-major": lambda f: obs_b.integrate(f.depth_m, f.K, f.T_W_C),
    }
    f0 = frames[int(picks[0])]
    for call in calls.values():  # compile
        call(f0)
    ms = {name: [] for name in calls}
    for i in picks:
        f = frames[int(i)]
        for name, call in calls.items():
            t0 = time.perf_counter()
            call(f)
            ms[name].append(1e3 * (time.perf_counter() - t0))
    print("\n| call | ms per frame (median) |\n|---|---|")
    for name, v in ms.items():
        print(f"| {name} | {np.median(v):.1f} |")
    S, h, _ = obs.finalize()
    S_b, h_b, _ = obs_b.finalize()
    same = np.array_equal(h[perm], h_b) and np.array_equal(S[perm][:, 13], S_b[:, 13])
    print(f"\nblock-major sums equal to the band order's (h and the diagonal): {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
