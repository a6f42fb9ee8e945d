#!/usr/bin/env python
"""Where do the posterior's gross held-out errors come from: false surfaces in front of the
measured depth, or missing ones behind it?

Reads an ``evalviews`` run folder (``band.npz`` and ``tsdf_mesh.ply``, e.g. one written by
``tools/evalviews_table.py``), renders the posterior (ray cast of ``mu = 0``) and the TSDF mesh at
every ``--every``-th frame of the first ``--frames`` of the dataset, and counts the pixels more
than 5 cm off for one method while the other is within 2 cm::

    python tools/evalviews_table.py --frames 0:100 --voxels 0.02 --no-open3d --out out/ev
    python tools/gross_errors.py out/ev/evalviews-2cm --frames 100 --every 10

With ``--carve``, also how the fused frames (the even ones) saw the voxel each ray-cast depth
lands in, for the posterior-only pixels in front and for the pixels within 1 cm (up to 2000 of
each, every tenth): how many frames carved it (saw it farther than the bootstrap truncation in
front of their surface, :mod:`kernels.carve`) and what share of the frames observing it that is
(``prior.carve`` is a threshold on it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("run", type=Path, help="run folder with band.npz and tsdf_mesh.ply")
    ap.add_argument("--data", default=str(DATA), help="the dataset the run fused")
    ap.add_argument("--frames", type=int, default=100, help="first N frames of the dataset")
    ap.add_argument("--every", type=int, default=10, help="frame step (odd offsets: held out)")
    ap.add_argument("--carve", action="store_true",
                    help="also the carve counts of the voxels the gross and the good pixels hit")
    args = ap.parse_args(argv)

    import numpy as np
    import trimesh

    from bftaichi.backend import init
    from bftaichi.formats import open_dataset
    from bftaichi.formats.synthetic import DepthRenderer
    from bftaichi.geometry import nearest_rigid, points_in_local, pose_in_local
    from bftaichi.io import read_mesh_ply
    from bftaichi.posterior import Posterior
    from kernels.raycast import raycast_depth

    init("cpu")
    post = Posterior.load(args.run / "band.npz")
    v, f, _ = read_mesh_ply(args.run / "tsdf_mesh.ply")  # world; rendered in the band's frame
    tsdf = DepthRenderer(trimesh.Trimesh(points_in_local(v, post.origin), f, process=False))
    ds = open_dataset(args.data)
    observed = (post.weight > 0).astype(np.uint8)
    front = behind = tsdf_only = pixels = 0
    # the mean error split by where the two methods are more than 5 cm off: pixels, and the
    # sums of |error| of the posterior and of the TSDF (metres)
    groups = {name: [0, 0.0, 0.0] for name in ("both within 5 cm", "posterior only off",
                                                "TSDF only off", "both off")}
    worse = {"posterior": [0, 0, 0], "TSDF": [0, 0, 0]}  # both off, worse by > 1 cm: all, both
    # in front of the measurement, both behind it
    hits = {"gross, in front": [], "within 1 cm": []}
    for i in range(1, min(args.frames, len(ds)), args.every):
        fr = ds[i]
        h, w = fr.depth_m.shape
        T = np.array(pose_in_local(fr.T_W_C, post.origin), np.float64)
        z = raycast_depth(post.band.block_keys, post.band.block_table, post.mean, observed,
                          post.voxel_size, fr.K, T, w, h, 0.1, 6.0)
        zt = tsdf.render(fr.K, nearest_rigid(T), w, h)
        D = fr.depth_m
        both = (z > 0) & (D > 0) & (zt > 0)
        e, et = z - D, zt - D
        post_only = both & (np.abs(e) > 0.05) & (np.abs(et) < 0.02)
        front += int(np.sum(post_only & (e < 0)))
        behind += int(np.sum(post_only & (e > 0)))
        tsdf_only += int(np.sum(both & (np.abs(et) > 0.05) & (np.abs(e) < 0.02)))
        pixels += int(both.sum())
        a, b = np.abs(e), np.abs(et)
        for name, sel in zip(groups, (both & (a <= 0.05) & (b <= 0.05),
                                      both & (a > 0.05) & (b <= 0.05),
                                      both & (a <= 0.05) & (b > 0.05),
                                      both & (a > 0.05) & (b > 0.05))):
            groups[name][0] += int(sel.sum())
            groups[name][1] += float(a[sel].sum())
            groups[name][2] += float(b[sel].sum())
        off = both & (a > 0.05) & (b > 0.05)
        for who, sel in (("posterior", off & (a > b + 0.01)), ("TSDF", off & (b > a + 0.01))):
            worse[who][0] += int(sel.sum())
            worse[who][1] += int(np.sum(sel & (e < 0) & (et < 0)))
            worse[who][2] += int(np.sum(sel & (e > 0) & (et > 0)))
        if args.carve:
            K_inv = np.linalg.inv(fr.K)
            for name, sel in (("gross, in front", post_only & (e < 0)),
                              ("within 1 cm", both & (np.abs(e) < 0.01))):
                vv, uu = np.nonzero(sel)
                vv, uu = vv[::10], uu[::10]
                rays = np.stack([uu, vv, np.ones_like(uu)]).astype(np.float64)
                p = (T[:3, :3] @ (K_inv @ rays * z[vv, uu])).T + T[:3, 3]
                hits[name].append(np.floor(p / post.voxel_size).astype(np.int32))
    print(f"{pixels} pixels where all three have depth; posterior > 5 cm off while the TSDF is "
          f"within 2 cm: {front} in front of the measured depth, {behind} behind; the TSDF > 5 cm "
          f"off while the posterior is within 2 cm: {tsdf_only}")
    print("the mean absolute error split by where each method is more than 5 cm off "
          "(share of the pixels; mm of the mean of the posterior / of the TSDF):")
    for name, (n, sp, st) in groups.items():
        print(f"  {name:20s} {100 * n / max(pixels, 1):6.2f} %  {1000 * sp / max(pixels, 1):7.2f}"
              f" / {1000 * st / max(pixels, 1):7.2f}")
    for who, (n, f_, b_) in worse.items():
        print(f"  both off, the {who} worse by more than 1 cm: {n} pixels ({f_} with both in "
              f"front of the measurement, {b_} with both behind it)")
    if args.carve:
        from kernels.carve import FreeSpaceCounter

        for name, ijk in hits.items():
            ijk = np.concatenate(ijk) if ijk else np.zeros((0, 3), np.int32)
            ijk = ijk[np.linspace(0, len(ijk) - 1, min(2000, len(ijk))).astype(int)]
            counter = FreeSpaceCounter(ijk, post.voxel_size, post.bootstrap_trunc_m)
            for i in range(0, min(args.frames, len(ds)), 2):
                fr = ds[i]
                counter.add(fr.depth_m, fr.K, pose_in_local(fr.T_W_C, post.origin))
            n, seen = counter.carved(), counter.observing()
            share = n / np.maximum(seen, 1)
            if len(ijk):
                print(f"{name}: {len(ijk)} voxels, carved by a median of {np.median(n):.0f} "
                      f"frames ({100 * np.median(share):.0f} % of those observing it); share "
                      f">= 20 / 40 %: {100 * np.mean(share >= 0.2):.0f} / "
                      f"{100 * np.mean(share >= 0.4):.0f} % of the voxels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
