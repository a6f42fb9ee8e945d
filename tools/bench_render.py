#!/usr/bin/env python
"""Time synthetic depth rendering: N frames of WxH from a mesh (default: the 70k-face bunny).

    python tools/bench_render.py                     # 100 frames of 320x240, Kinect noise
    python tools/bench_render.py --frames 20 --mesh tabletop
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
BUNNY = ROOT.parent / "shared" / "data" / "meshes" / "stanford-bunny.obj"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--mesh", default=str(BUNNY), help="mesh file or primitive name")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    args = ap.parse_args(argv)

    from bftaichi.config import SyntheticConfig
    from bftaichi.formats.synthetic import SyntheticDataset

    scale = args.width / 320
    cfg = SyntheticConfig(mesh=args.mesh, mesh_up="y" if args.mesh.endswith(".obj") else "z",
                          center_mesh=True, trajectory="ring", n_views=args.frames,
                          cam_radius_m=0.5 if args.mesh == str(BUNNY) else 1.2, cam_height_m=0.2,
                          width=args.width, height=args.height, fx=262.5 * scale, fy=262.5 * scale,
                          cx=(args.width - 1) / 2, cy=(args.height - 1) / 2)
    t0 = time.perf_counter()
    ds = SyntheticDataset(cfg)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    valid = sum(int((f.depth_m > 0).sum()) for f in ds)
    t_render = time.perf_counter() - t0
    print(f"mesh: {args.mesh} ({len(ds.gt_mesh.faces):,} faces), load {t_load:.2f} s")
    print(f"rendered {args.frames} frames of {args.width}x{args.height} with noise in "
          f"{t_render:.2f} s ({args.frames / t_render:.1f} frames/s, {valid:,} valid pixels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
