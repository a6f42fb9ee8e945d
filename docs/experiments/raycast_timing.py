"""Time and hash the predicted depth of two runs' posteriors (issue 18: docs/measurements.md,
"The raycast crosses blocks without a crossing in two samples").

Casts the 48 hemisphere candidates of a bowl run (160 x 120) and 12 redkitchen poses (frames 0,
40, ..., 480) into a 2 cm fuse (640 x 480, with the depth's sigma), three rounds each, and prints
a hash of every image of the first round and the milliseconds a cast. The ``bftaichi`` imported
is the one of the current directory's checkout, so that ``tools/alternate.py`` can run the
script from one place in several checkouts, older ones included::

    bftaichi run scenes/bowl.toml --out /tmp/bowl
    bftaichi fuse ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out /tmp/k2
    python tools/alternate.py ../before . --rounds 4 --pattern "kitchen ([0-9.]+) ms" -- \\
        python $PWD/docs/experiments/raycast_timing.py /tmp/bowl/band.npz /tmp/k2/band.npz \\
        $PWD/../shared/data/rgbd/7scenes-redkitchen
"""

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(os.getcwd())  # the checkout measured: the current directory's (see above)
sys.path.insert(0, str(ROOT))

BOWL_K = np.array([[131.25, 0.0, 79.5], [0.0, 131.25, 59.5], [0.0, 0.0, 1.0]])  # scenes/bowl.toml


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bowl", help="band.npz of `bftaichi run scenes/bowl.toml`")
    ap.add_argument("kitchen", help="band.npz of a 2 cm redkitchen fuse")
    ap.add_argument("data", help="the redkitchen frames (for their poses and intrinsics)")
    args = ap.parse_args()
    import bftaichi as bf
    from bftaichi.geometry import pose_in_local
    from bftaichi.planning.nbv import candidates_around
    from kernels.raycast import raycast_depth

    bf.init("cpu")
    frames = bf.open_dataset(args.data, frames=slice(0, 500, 40))
    digest, ms = hashlib.sha256(), {}
    runs = (("bowl", args.bowl, (160, 120)), ("kitchen", args.kitchen, (640, 480)))
    for name, path, size in runs:
        post = bf.Posterior.load(path)
        if name == "bowl":
            poses, K = candidates_around(post, 48), BOWL_K
        else:
            poses, K = [f.T_W_C for f in frames], frames[0].K
        observed = (post.weight > 0).astype(np.uint8)

        def cast(T):
            return raycast_depth(post.band.block_keys, post.band.block_table, post.mean,
                                 observed, post.voxel_size, K, pose_in_local(T, post.origin),
                                 size[0], size[1], 0.1, 6.0, var=post.var)
        cast(poses[0])  # compiles
        t0 = time.perf_counter()
        for round_ in range(3):
            for T in poses:
                depth, sigma = cast(T)
                if round_ == 0:
                    digest.update(depth.tobytes())
                    digest.update(sigma.tobytes())
        ms[name] = 1e3 * (time.perf_counter() - t0) / (3 * len(poses))
    print(f"{ROOT}: hash {digest.hexdigest()[:16]}, bowl {ms['bowl']:.2f} ms, "
          f"kitchen {ms['kitchen']:.2f} ms a cast")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
