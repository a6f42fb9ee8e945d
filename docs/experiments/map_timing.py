"""The MAP solve of a fuse, timed on its own (issue 16; docs/measurements.md, "The MAP's local
passes without their Python overhead").

``dump`` runs ``bftaichi fuse`` in this process until the MAP solve and saves what
``bftaichi.stages.solve.solve_map`` is given (the system before it changes it in place);
``time`` solves that system again, several times in one process, and prints the seconds, a hash
of the mean and of the system as returned (the same hash = the same bytes), and the PCG counts.
Run ``time`` from two checkouts (each its own copy of this script) to compare builds::

    python docs/experiments/map_timing.py dump ../shared/data/rgbd/7scenes-redkitchen 0.01 /tmp/map1.pkl
    python docs/experiments/map_timing.py time /tmp/map1.pkl --repeats 2
    python ../before/docs/experiments/map_timing.py time /tmp/map1.pkl --repeats 2

The system of a 1 cm fuse of the 500 redkitchen frames takes 1.4 GB on disk.
"""
import argparse
import copy
import hashlib
import pickle
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402


class _Stop(Exception):
    pass


def dump(data: str, voxel: str, path: str) -> None:
    import bftaichi.stages.bandsolve as bandsolve
    from bftaichi.cli import main

    def grab(system, x0, solver, band, **kw):
        with open(path, "wb") as f:
            pickle.dump((copy.deepcopy(system), x0.copy(), solver, band, kw), f, protocol=5)
        raise _Stop

    bandsolve.solve_map = grab
    try:
        main(["fuse", data, "--voxel", voxel, "--out", path + ".run", "--overwrite"])
    except (_Stop, SystemExit):
        pass
    print(f"saved {path}")


def solve(path: str, repeats: int) -> None:
    from bftaichi import backend
    from bftaichi.stages.solve import solve_map

    backend.init("cpu")
    for _ in range(repeats):
        with open(path, "rb") as f:
            system, x0, solver, band, kw = pickle.load(f)
        t = time.perf_counter()
        mean, stats = solve_map(system, x0, solver, band, **kw)
        seconds = time.perf_counter() - t
        digest = hashlib.sha256()
        for a in (mean, system.S, system.h):
            digest.update(np.ascontiguousarray(a).tobytes())
        print(f"{seconds:.2f} s  hash {digest.hexdigest()[:16]}  iterations "
              f"{stats['iterations']}, local solves {stats['local_solves']} "
              f"({stats['local_iterations']} iterations)", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="fuse until the MAP, save its inputs")
    d.add_argument("data")
    d.add_argument("voxel")
    d.add_argument("path")
    t = sub.add_parser("time", help="solve a saved MAP system again, timed")
    t.add_argument("path")
    t.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)
    if args.cmd == "dump":
        dump(args.data, args.voxel, args.path)
    else:
        solve(args.path, args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
