#!/usr/bin/env python
"""The super-pixel pyramid of real frames, as the observation pass builds it for every frame
(``Observer._levels``: :func:`kernels.dataterm.superpixels` and its Python around it):
milliseconds per frame, and one hash of every level's image and mask over all the frames, so
two builds can be compared for speed and for the same bytes::

    python tools/bench_superpixels.py                     # redkitchen, 2 cm
    python tools/bench_superpixels.py --voxel 0.01
    (cd ../before && python tools/bench_superpixels.py)   # a worktree of another build

The frames (every tenth of the first 400) are preloaded and the kernel compiled first; the
Observer has the default observation model (a one-voxel band: the pyramid does not depend on
it). Printed: the median and best of ``--repeats`` passes over the frames. One run on a shared
machine is noisy: alternate the builds.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import checkout  # noqa: F401  (this checkout's bftaichi and kernels first on sys.path)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd" / "7scenes-redkitchen"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="?", default=str(DATA), help="a dataset folder")
    ap.add_argument("--voxel", type=float, default=0.02, help="voxel size, metres")
    ap.add_argument("--repeats", type=int, default=5, help="passes over the frames")
    args = ap.parse_args(argv)

    import numpy as np

    from bftaichi import backend
    from bftaichi.config import Config
    from bftaichi.formats import open_dataset
    from bftaichi.stages.observe import make_observer
    from kernels.lookup import build_block_table

    backend.init("cpu")
    dataset = open_dataset(args.data)
    frames = [dataset[i] for i in range(0, min(400, len(dataset)), 10)]

    class OneVoxel:  # what make_observer reads of a band
        ijk = np.zeros((1, 3), np.int32)
        block_keys, block_table = build_block_table(ijk)
        reference = np.full(1, np.nan, np.float32)

        def __len__(self):
            return 1

    cfg = Config()
    obs = make_observer(OneVoxel(), cfg.observation, args.voxel, 2 * args.voxel)
    params = [obs._frame_params(f.depth_m, f.K, f.T_W_C, None) for f in frames]
    obs._levels(*params[0], 1)  # compiles
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        for depth, prm in params:
            obs._levels(depth, prm, 1)
        times.append((time.perf_counter() - t0) / len(params) * 1e3)
    digest = hashlib.sha256()
    for depth, prm in params:
        for image, mask, _, k in obs._levels(depth, prm, 1):
            digest.update(np.int64(k).tobytes() + image.tobytes() + mask.tobytes())
    print(f"super-pixels, {args.voxel * 100:g} cm, {len(params)} frames: median "
          f"{np.median(times):.2f} ms a frame, best {min(times):.2f}; levels' images and masks "
          f"sha256 {digest.hexdigest()[:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
