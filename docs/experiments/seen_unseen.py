#!/usr/bin/env python
"""Where a run's Chamfer distance comes from: the part of the true surface its frames saw, or
the part none saw (a diagnosis for issue 15's geometry targets).

For a synthetic run folder (``bftaichi run`` of a synthetic scene, e.g. one case of
``tools/suite.py``), the true mesh is sampled as ``geometry_metrics`` samples it (200k points,
seed 0, ``cfg.eval``), and each true sample is *seen* when at least one of the run's frames
observed it: it projects into the frame with a valid depth within 3 times the frame's axial
noise (plus 1 mm) of its own camera depth, i.e. nothing hid it (``seen_samples`` of
tools/suite.py, as the suite splits it). Each predicted sample takes the class of the true
sample nearest to it. Printed per mesh (``mesh.ply``, ``tsdf_mesh.ply``): the accuracy
(predicted to true, mean) and, per class, the completeness (true to predicted, mean) and the
class's part of the Chamfer distance, ``mean(d_pg^2) + mean(d_gp^2)`` summed over that class's
samples only (the two parts add up to the run's ``chamfer_l2``:
``SampledSurface.chamfer_split``), and the F-score at ``--f-mm`` over all the true samples and
over the seen ones (precision over the predicted samples nearest to them)::

    python docs/experiments/seen_unseen.py OUT_DIR [OUT_DIR ...]
    python tools/suite.py --heldout --meshes disk --conditions few_views --keep runs
    python docs/experiments/seen_unseen.py runs/disk-few_views

The frames are rendered again from the run's ``config.toml`` (the same seed, the same noise).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))  # tools/suite.py
sys.path.insert(0, str(ROOT))  # this checkout's bftaichi first


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders of synthetic scenes")
    ap.add_argument("--f-mm", type=float, default=1.0,
                    help="F-score threshold, mm (default 1); on the seen part a predicted sample "
                    "counts with its nearest true sample's class")
    args = ap.parse_args(argv)

    import trimesh

    import bftaichi as bf
    from suite import seen_samples

    for run in args.runs:
        cfg = bf.load_config(run / "config.toml", [])
        if cfg.scene.source != "synthetic":
            raise SystemExit(f"seen_unseen: {run} is not a synthetic scene (no true mesh)")
        target, seen = seen_samples(cfg)  # as the suite splits it
        print(f"{run}: {100 * seen.mean():.1f} % of the true surface seen")
        for name in ("mesh.ply", "tsdf_mesh.ply"):
            pred = trimesh.load(run / name, process=False)
            matched = target.match(pred)
            d_pg, nearest, d_gp = matched
            part_seen, part_unseen = target.chamfer_split(pred, seen, matched=matched)
            cd = part_seen + part_unseen
            print(f"  {name}: chamfer_l2 {cd:.3e}, accuracy {1000 * d_pg.mean():.3f} mm")
            t = args.f_mm / 1000.0
            for label, p_in, g_in in (("all", slice(None), slice(None)),
                                      ("seen", seen[nearest], seen)):
                prec, rec = np.mean(d_pg[p_in] < t), np.mean(d_gp[g_in] < t)
                f = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
                print(f"    F@{args.f_mm:g}mm, {label} true samples: {f:.3f} "
                      f"(precision {prec:.3f}, recall {rec:.3f})")
            for label, g, part in (("seen", seen, part_seen), ("unseen", ~seen, part_unseen)):
                comp = 1000 * d_gp[g].mean() if g.any() else float("nan")
                print(f"    {label:6s}: completeness {comp:.3f} mm, CD part {part:.3e} "
                      f"({100 * part / cd:.0f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
