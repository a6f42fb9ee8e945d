"""How much of a real sequence's consecutive frames one observation could carry (issue 16; a
measurement for a lead, nothing built: docs/measurements.md, "Consecutive frames seen as one").

The observation pass casts rays per frame. Frames of a 30 fps sequence see nearly the same
surface from nearly the same pose; if a group of ``K`` consecutive frames were observed as one
(each pixel of the group's first frame carrying the depths of the later frames that land on
it, their information summed), the pass would cast one frame's rays, plus one ray for every
pixel of the later frames that cannot be merged. For groups of ``--group`` frames of the
sequence, this prints:

1. the share of a later frame's valid pixels that land, through the recorded poses, on a
   valid pixel of the group's first frame (nearest pixel, in front of it, within ``--tol``
   times the depth noise of the Kinect model, ``sqrt 2`` for the two frames) and are the only
   pixel of their frame to land there: mergeable; the rest are the leftovers;
2. the rays the current pass casts for the group (each frame's super-pixel pyramid,
   ``observation.aggregate`` at ``--voxel``) against the first frame's rays plus one ray per
   leftover pixel, an upper bound of what merging would cast (leftovers that form blocks cast
   fewer)::

    python docs/experiments/frame_merge_overlap.py                   # frames 0-99, groups of 2 and 4
    python docs/experiments/frame_merge_overlap.py --frames 0:500:1 --group 4 --voxel 0.01
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def mergeable(ref, frame, tol: float, a: float, b: float, z0: float) -> np.ndarray:
    """Pixels of ``frame`` against ``ref`` (module docstring, 1): (valid, landing on the
    image in front of ``ref``, of those on a valid pixel within the tolerance, of those the
    only one there = mergeable)."""
    d = frame.depth_m
    v, u = np.nonzero(d > 0)
    z = d[v, u].astype(np.float64)
    K = np.asarray(frame.K, np.float64)
    x = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    T = np.linalg.inv(np.asarray(ref.T_W_C, np.float64)) @ np.asarray(frame.T_W_C, np.float64)
    y = x @ T[:3, :3].T + T[:3, 3]
    Kr = np.asarray(ref.K, np.float64)
    ok = y[:, 2] > 1e-6
    ur = np.rint(Kr[0, 0] * y[:, 0] / np.where(ok, y[:, 2], 1) + Kr[0, 2]).astype(np.int64)
    vr = np.rint(Kr[1, 1] * y[:, 1] / np.where(ok, y[:, 2], 1) + Kr[1, 2]).astype(np.int64)
    H, W = ref.depth_m.shape
    ok &= (ur >= 0) & (ur < W) & (vr >= 0) & (vr < H)
    in_view = int(ok.sum())
    dr = np.where(ok, ref.depth_m[np.clip(vr, 0, H - 1), np.clip(ur, 0, W - 1)], 0.0)
    sigma = a + b * (y[:, 2] - z0) ** 2
    ok &= (dr > 0) & (np.abs(dr - y[:, 2]) <= tol * np.sqrt(2.0) * sigma)
    consistent = int(ok.sum())
    target = vr * W + ur
    hits = np.bincount(target[ok], minlength=H * W)
    ok &= hits[np.where(ok, target, 0)] == 1
    return np.array([len(z), in_view, consistent, int(ok.sum())])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", type=Path, default=DATA)
    ap.add_argument("--frames", default="0:100:1", help="start:stop:step of the sequence")
    ap.add_argument("--group", default="2,4", help="group sizes, comma-separated")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--tol", type=float, default=3.0, help="consistency, in depth-noise sigmas")
    args = ap.parse_args()
    import bftaichi as bf
    from bftaichi import backend
    from kernels.observe import Observer

    backend.init()

    start, stop, step = (int(x) for x in args.frames.split(":"))
    cfg = bf.load_config(None, [f"tsdf.voxel_size_m={args.voxel}"])
    o = cfg.observation
    frames = list(bf.open_dataset(args.data, frames=slice(start, stop, step)))
    obs = Observer(np.zeros(0, np.int64), np.zeros((0, 512), np.int32), 0, args.voxel,
                   2 * args.voxel, count_once="voxel", front_m=4 * args.voxel, gate_m=0.0,
                   aggregate=o.aggregate)

    def rays(frame) -> int:
        depth, prm = obs._frame_params(frame.depth_m, frame.K, frame.T_W_C, None)
        return sum(int(np.count_nonzero(mask == 1)) for _, mask, _, _ in
                   obs._levels(depth, prm, 1))

    n_rays = [rays(f) for f in frames]
    print(f"{len(frames)} frames, {args.voxel * 100:g} cm; rays a frame (super-pixels): "
          f"median {np.median(n_rays):,.0f}")
    print("| group | later frames' pixels in view / consistent / mergeable | leftover pixels a "
          "group | rays a group now | rays merged (at most) | ratio |")
    print("|---|---|---|---|---|---|")
    for K in (int(k) for k in args.group.split(",")):
        counts = np.zeros(4, np.int64)
        left = now = after = 0
        groups = 0
        for g in range(0, len(frames) - K + 1, K):
            ref = frames[g]
            group_left = 0
            for f in frames[g + 1:g + K]:
                c = mergeable(ref, f, args.tol, o.depth_a_m, o.depth_b, o.depth_z0_m)
                counts += c
                group_left += int(c[0] - c[3])
            now += sum(n_rays[g:g + K])
            after += n_rays[g] + group_left
            left += group_left
            groups += 1
        share = " / ".join(f"{100 * x / max(counts[0], 1):.1f}" for x in counts[1:])
        print(f"| {K} | {share} % | {left / max(groups, 1):,.0f} | "
              f"{now / groups:,.0f} | {after / groups:,.0f} | {after / max(now, 1):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
