"""Block-Jacobi PCG for the probes (issue 16; measured, not built: docs/measurements.md,
"Block Jacobi for the probes").

Apply ``docs/experiments/block_jacobi_probes.patch`` (``git apply``: ``kernels/blockjacobi.py``,
a ``precond`` argument for ``kernels.pcg``), dump a MAP system with
``docs/experiments/preconditioners.py dump``, then time the 16 colouring probes of the
variance stage with Jacobi and with the 2 x 2 x 2 blocks, twice each::

    python docs/experiments/preconditioners.py dump /tmp/sys.npz fuse \\
        ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out /tmp/k2 -q
    python docs/experiments/block_jacobi_probes.py /tmp/sys.npz /tmp/k2/band.npz
"""
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def main(system_path, band_path) -> None:
    from bftaichi import backend

    backend.init("cpu")
    from kernels.blockjacobi import BlockJacobi
    from kernels.pcg import pcg_batched
    from kernels.probes import probe_vectors

    d = np.load(system_path)
    S, nbr = d["S"], d["nbr"]
    far = (d["S2"], d["nbr2"]) if d["S2"].ndim == 2 else None
    ijk = np.load(band_path)["ijk"]
    Z = probe_vectors(len(S), 16, 0, method="coloring", ijk=ijk)
    t = time.perf_counter()
    bj = BlockJacobi(S, ijk)
    print(f"blocks: {bj.n_aggregates:,} aggregates of {len(S):,} voxels, {bj.nbytes / 1e6:.1f} MB, "
          f"built in {time.perf_counter() - t:.2f} s")
    s0 = None
    for _ in range(2):
        for name, pc in (("jacobi", None), ("block", bj)):
            t = time.perf_counter()
            U, info = pcg_batched(S, nbr, Z, None, 1e-3, 2000, np.float32, check=False, far=far,
                                  precond=pc)
            dt = time.perf_counter() - t
            s = (Z * U).sum(1) / (Z * Z).sum(1)
            s0 = s if s0 is None else s0
            print(f"{name}: {dt:.3f} s, iterations {info['iterations']}, median |s - s_jacobi| "
                  f"/ s {np.median(np.abs(s - s0) / s0):.1e}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
