#!/usr/bin/env python
"""Is the real frames' extra noise shared by frames close in time? (issue 15; a diagnosis)

The noise fit (:func:`bftaichi.stages.observe.estimate_extra_noise`) pairs 16 frames spread
over a sequence and finds the noise the sensor model does not explain (pose and calibration
errors), which the observation model then treats as independent from frame to frame. This
script fits the same statistic to pairs of frames ``g`` fused frames apart only (12 anchors
spread over the sequence, each paired with the frame ``g`` later; the pairs' cut and fit of
the noise fit itself) for ``g`` = 1 .. 64. With independent frames every gap gives the same
noise; if consecutive frames share their pose error, the close pairs' difference holds less
of it::

    python docs/experiments/pose_noise_in_time.py                       # 7-Scenes redkitchen
    python docs/experiments/pose_noise_in_time.py --voxel 0.01
    python docs/experiments/pose_noise_in_time.py --case homer/dense_near --gaps 1,2,4,8,16,32

It prints, per gap, the pairs, the fitted noise ``e_g`` and ``rho_g = 1 - e_g^2 / e_far^2``,
the correlation of two frames' extra noise at that gap (``e_far`` the largest gap's ``e``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?",
                    default=str(ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"))
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--frames", default="0:500:2", help="the fused frames (evalviews' half)")
    ap.add_argument("--gaps", default="1,2,4,8,16,32,64")
    ap.add_argument("--anchors", type=int, default=12)
    ap.add_argument("--case", help="a development-suite case instead, e.g. homer/dense_near")
    args = ap.parse_args(argv)

    import bftaichi as bf
    import bftaichi.stages.observe as ob
    from bftaichi.stages.pairmodel import fit_extra
    from bftaichi.frame import local_frames
    from bftaichi.running.pipeline import open_frames
    from bftaichi.stages.band import build_band

    if args.case:  # a development-suite case, rendered as tools/suite.py renders it
        from suite import case_sets
        mesh, condition = args.case.split("/")
        cfg = bf.load_config(None, case_sets(mesh, condition, ROOT.parent / "shared" / "data"))
        args.voxel = cfg.tsdf.voxel_size_m
    else:
        cfg = bf.load_config(None, ["scene.source=dataset", f'scene.data="{args.data}"',
                                    f"tsdf.voxel_size_m={args.voxel}",
                                    f"tsdf.trunc_m={2 * args.voxel}",
                                    f'scene.frames="{args.frames}"'])
    recon = bf.Reconstructor(cfg)
    for f in open_frames(cfg):
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    frames = local_frames(recon.frames, recon.origin)
    observed = band.observed.astype(np.uint8)
    cache = {}

    def cast(i: int):
        """The noise fit's cast of frame i (its residuals against the bootstrap)."""
        if i not in cache:
            cache[i] = ob._cast_frame(frames[i], band, observed, args.voxel,
                                      cfg.tsdf.bootstrap_trunc_m,
                                      (cfg.scene.depth_min_m, cfg.scene.depth_max_m))
        return cache[i]

    gaps = [int(g) for g in args.gaps.split(",")]
    anchors = np.linspace(0, len(frames) - 1 - max(gaps), args.anchors).round().astype(int)
    fits = []
    for g in gaps:
        pairs = []
        for a in anchors:
            pairs += ob._pair_candidates([cast(a), cast(a + g)], cfg.observation, None)
        e = 0.0
        for _ in range(ob._CUT_ROUNDS):
            r, s, t, _shared = ob._cut_pairs(pairs, args.voxel, e)
            e_new = fit_extra(r, s, t)
            done = abs(e_new - e) <= 0.005 * max(e_new, 1e-6)
            e = e_new
            if done:
                break
        fits.append((g, len(r), e, float(np.median(r))))
    e_far = fits[-1][2]
    print("| gap (fused frames) | pairs | median abs d (mm) | e_g (mm) | rho_g |")
    print("|---|---|---|---|---|")
    for g, n, e, med in fits:
        rho = 1.0 - (e / e_far) ** 2 if e_far > 0 else float("nan")
        print(f"| {g} | {n} | {med * 1e3:.2f} | {e * 1e3:.2f} | {rho:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
