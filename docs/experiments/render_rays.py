"""The synthetic renderer's pixel rays by the diagonal's reciprocals instead of
``np.linalg.solve`` (:func:`bftaichi.geometry.pixel_rays`, the default since:
docs/measurements.md, "The synthetic renderer's rays").

For random pinhole matrices (last row exactly (0, 0, 1)) and the image sizes the scenes use,
checks that :func:`~bftaichi.geometry.pixel_rays`, ``(u - cx) * (1 / fx), (v - cy) * (1 /
fy)``, has the bits of ``np.linalg.solve(K, [u, v, 1])`` (divided by its z, which is 1), and
times both::

    python docs/experiments/render_rays.py
    python docs/experiments/render_rays.py --matrices 1000
"""
import argparse
import sys
import time

from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)
from bftaichi.geometry import pixel_rays  # noqa: E402

SIZES = ((640, 480), (320, 240), (160, 120))


def by_solve(K, u, v):
    pix = np.stack([u, v, np.ones(u.size)], axis=0)
    d = np.linalg.solve(K, pix)
    d /= d[2]
    return d


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--matrices", type=int, default=200, help="random K per size (default 200)")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    for w, h in SIZES:
        u, v = (a.ravel() for a in np.meshgrid(np.arange(w, dtype=np.float64),
                                               np.arange(h, dtype=np.float64)))
        differ, t_solve, t_recip = 0, 0.0, 0.0
        for _ in range(args.matrices):
            K = np.array([[rng.uniform(50, 2000), 0, rng.uniform(0, w)],
                          [0, rng.uniform(50, 2000), rng.uniform(0, h)], [0, 0, 1]])
            t0 = time.perf_counter()
            a = by_solve(K, u, v)
            t1 = time.perf_counter()
            b = pixel_rays(K, w, h)
            t2 = time.perf_counter()
            differ += not np.array_equal(a, b)
            t_solve += t1 - t0
            t_recip += t2 - t1
        n = args.matrices
        print(f"{w}x{h}: {differ} of {n} matrices differ in any bit; solve {1e3 * t_solve / n:.2f} "
              f"ms, reciprocals {1e3 * t_recip / n:.2f} ms a frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
