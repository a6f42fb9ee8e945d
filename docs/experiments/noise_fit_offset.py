#!/usr/bin/env python
"""The noise fit on synthetic captures, with pairs restricted to nearly the same point (issue 15;
a diagnosis, nothing built).

The synthetic captures of ``tools/suite.py`` have the observation model's own Kinect noise and a
1 mm quantisation (0.29 mm std): a noise fit (:func:`bftaichi.stages.observe.estimate_extra_noise`)
should find almost no extra noise there. It pairs a cast pixel of one frame with the nearest
cast pixel of another, whose centre can lie up to half a (cast) pixel from the projected
point; where a pixel spans a voxel or more, the bootstrap's error differs between the two
points and reads as noise. This prints the fit with every pair, and with only the pairs whose
projection falls within ``--offsets`` pixels of the paired pixel's centre::

    python docs/experiments/noise_fit_offset.py suzanne/sparse_far stanford-bunny/dense_near
    python docs/experiments/noise_fit_offset.py suzanne/heavy_noise --stride 1

(The fit returns 0 from fewer than 100 pairs: a restriction that leaves fewer says nothing.)
"""

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("cases", nargs="+", help="MESH/CONDITION, e.g. suzanne/sparse_far")
    ap.add_argument("--offsets", type=float, nargs="+", default=[0.25, 0.1])
    ap.add_argument("--stride", type=int, default=4, help="cast every STRIDE-th pixel (the "
                    "fit's default 4; 1 pairs every pixel with its nearest)")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    args = ap.parse_args(argv)

    import suite
    import bftaichi as bf
    from bftaichi.frame import local_frames
    from bftaichi.formats.synthetic import SyntheticDataset
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import estimate_extra_noise

    for case in args.cases:
        mesh, condition = case.split("/")
        cfg = bf.load_config(None, suite.case_sets(mesh, condition, args.data))
        frames = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
        recon = bf.Reconstructor(cfg)
        for f in frames:
            recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
        band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
        local = local_frames(recon.frames, recon.origin)
        o = cfg.observation
        rng = (cfg.scene.depth_min_m, cfg.scene.depth_max_m)
        for off in (None, *args.offsets):
            fit = estimate_extra_noise(local, band, o, cfg.tsdf.voxel_size_m,
                                       cfg.tsdf.bootstrap_trunc_m, rng, max_offset_px=off,
                                       stride=args.stride)
            print(f"{case} (stride {args.stride}): pairs within {'any' if off is None else f'{off:g} px'}: "
                  f"extra {1e3 * fit['sigma_extra_m']:.2f} mm, shared "
                  f"{1e3 * fit['sigma_corr_m']:.2f} mm, {fit['pixels']} pairs", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
