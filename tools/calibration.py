#!/usr/bin/env python
"""Is sigma honest? Calibration of the posterior against the known truth (DESIGN.md section 6).

Runs a scene with a ground-truth mesh (default: the noisy Stanford bunny, ``scenes/bunny.toml``)
once per variant and, over the observed band voxels within ``--near`` voxels of the true surface,
compares the error ``e = mean - phi_true`` (``phi_true``: signed distance to the ground-truth
mesh, :func:`bftaichi.evaluation.metrics.surface_sdf`) with the posterior sigma:

- coverage of ``|e| <= k sigma`` for k = 1, 2, 3 (a Gaussian gives 68.3 / 95.4 / 99.7 %),
- the median of ``|e| / sigma`` (0.674 for a Gaussian; below: sigma too large),
- the Spearman rank correlation between sigma and ``|e|``, and AUSE (mm),
- the posterior mesh's Chamfer distance next to the TSDF's.

Variants (rows): the defaults; without the three additions made for real data (side gate,
noise fit, free-space constraint); ``count_once=pixel`` (each pixel's information split over all its
samples, DESIGN.md 3.3); the paper's prior (membrane + boundary anchors, no curvature term).
Pass ``--only default`` to run the first row alone. Every figure of the README's calibration
table comes from this script::

    python tools/calibration.py                              # bunny, three variants
    python tools/calibration.py scenes/bunny_far.toml --only default
    python tools/calibration.py --set observation.sigma_model_m=0.002 --markdown calib.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NO_REAL_DATA_ADDITIONS = ["observation.gate=0", "observation.fit_noise=false", "prior.free=0"]
VARIANTS = {
    "default": [],
    "no gate, noise fit, free space": NO_REAL_DATA_ADDITIONS,
    "count_once=pixel": ["observation.count_once=pixel"],
    "samples within +-tau (front=1)": ["observation.front=1"],
    "paper model (membrane + anchors, +-tau)": ["prior.curvature=0", "prior.lam=0.01",
                                                "prior.anchors=boundary", "observation.front=1",
                                                *NO_REAL_DATA_ADDITIONS],
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(ROOT / "scenes" / "bunny.toml"),
                    help="scene file with ground truth (default: scenes/bunny.toml)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override applied to every variant")
    ap.add_argument("--near", type=float, default=1.0,
                    help="evaluate voxels with |true SDF| <= NEAR voxels (default 1)")
    ap.add_argument("--only", choices=list(VARIANTS), help="run one variant only")
    ap.add_argument("--markdown", type=Path, help="also write the table as Markdown here")
    args = ap.parse_args(argv)

    import bftaichi as bf
    from bftaichi.errors import BftaichiError

    rows = []
    for name, sets in VARIANTS.items():
        if args.only and name != args.only:
            continue
        try:
            cfg = bf.load_config(args.scene, [*sets, *args.sets,
                                              f"eval.near_voxels={args.near}"])
        except BftaichiError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        with tempfile.TemporaryDirectory(prefix="bftaichi-calib-") as tmp:
            report = bf.run(cfg, Path(tmp), progress=False)
        u = report.get("uncertainty")
        if not u:
            print(f"error: {args.scene} has no ground truth (or no observed voxel near it): "
                  "calibration needs one", file=sys.stderr)
            return 2
        m = report["metrics"]
        rows.append((name, u, m["tsdf_mesh.ply"]["chamfer_l2"], m["mesh.ply"]["chamfer_l2"]))
        print(f"{name}: done ({u['n']} voxels)", file=sys.stderr, flush=True)

    head = ("| variant | voxels | RMS error [mm] | median sigma [mm] | within 1 / 2 / 3 sigma [%] "
            "| median abs(e)/sigma | Spearman | AUSE [mm] | CD tsdf / mesh [m^2] |")
    lines = [f"Calibration on `{Path(args.scene).name}`: observed band voxels within "
             f"{args.near:g} voxel of the true surface (Gaussian: 68.3 / 95.4 / 99.7 %, median "
             "0.674).", "", head, "|" + "---|" * 9]
    for name, u, cd_t, cd_m in rows:
        lines.append(
            f"| {name} | {u['n']} | {u['rms_error_m'] * 1e3:.2f} | {u['median_sigma_m'] * 1e3:.2f} "
            f"| {u['coverage@1sigma'] * 100:.1f} / {u['coverage@2sigma'] * 100:.1f} / "
            f"{u['coverage@3sigma'] * 100:.1f} | {u['median_z']:.2f} | {u['spearman']:.2f} | "
            f"{u['ause'] * 1e3:.3f} | {cd_t:.3g} / {cd_m:.3g} |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        args.markdown.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
