"""Taichi's per-call Python overhead against the short launch path and a launch with its
arguments bound once (issues 16 and 18: docs/measurements.md, "Speed measurements that found
nothing to build" and "Kernel launches without Taichi's per-call Python path").

Times PCG's ``update_p`` (:class:`kernels.stencil.GatherKernels`, float64) on ``--voxels``
rows and ``--lanes`` columns called through Taichi's own ``Kernel.__call__`` (it checks and
sets every argument on every call), as a ``@ti.kernel`` call (since :mod:`kernels.launch`, the
short path :func:`bftaichi.init` installs), and launched directly from its compiled data with a
launch context whose arguments were set once (Taichi 1.7's private ``make_launch_context`` /
``launch_kernel``), and checks that all give the same bytes::

    python docs/experiments/launch_overhead.py                   # the bowl's scan-step band
    python docs/experiments/launch_overhead.py --voxels 10       # the launch alone
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def bound(kernel, *args):
    """A no-argument callable launching ``kernel`` on ``args`` (numpy arrays stay referenced)."""
    import taichi as ti
    from taichi.lang import impl
    from taichi.types import ndarray_type, primitive_types

    kernel = getattr(kernel, "_primal", kernel)
    t_kernel = kernel.compiled_kernels[kernel.ensure_compiled(*args)]
    prog = impl.get_runtime().prog
    compiled = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
    ctx = t_kernel.make_launch_context()
    j = 0
    for arg, v in zip(kernel.arguments, args):
        ann = arg.annotation
        if isinstance(ann, ti.template):
            continue
        if isinstance(ann, ndarray_type.NdarrayType):
            shape = v.shape
            if not (ann.dtype is None or id(ann.dtype) in primitive_types.type_ids):
                shape = v.shape[:-ann.dtype.ndim]  # vector elements: the array's own shape
            ctx.set_arg_external_array_with_shape((j,), int(v.ctypes.data), v.nbytes, shape, 0)
        elif ann in primitive_types.integer_types:
            ctx.set_arg_int((j,), int(v))
        else:
            ctx.set_arg_float((j,), float(v))
        j += 1
    return lambda: prog.launch_kernel(compiled, ctx), args


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--voxels", type=int, default=52864)
    ap.add_argument("--lanes", type=int, default=1)
    ap.add_argument("--calls", type=int, default=300)
    args = ap.parse_args()
    from bftaichi import backend
    from kernels.stencil import gather_kernels

    backend.init()
    rng = np.random.default_rng(0)
    n, lanes = args.voxels, args.lanes
    ker = gather_kernels(lanes, np.float64)
    R, P = rng.random((n + 1, lanes)), rng.random((n + 1, lanes))
    dinv, beta, active = rng.random(n), np.full(lanes, 0.5), np.ones(lanes, np.int32)
    from taichi.lang import kernel_impl

    taichi_path = getattr(kernel_impl.Kernel.__call__, "__wrapped__", kernel_impl.Kernel.__call__)
    primal = ker.update_p._primal
    P0, P1, P2 = P.copy(), P.copy(), P.copy()
    ker.update_p(beta, active, R, dinv, P1)
    launch, _keep = bound(ker.update_p, beta, active, R, dinv, P2)
    launch()
    taichi_path(primal, beta, active, R, dinv, P0)
    for rep in range(3):
        t0 = time.perf_counter()
        for _ in range(args.calls):
            taichi_path(primal, beta, active, R, dinv, P0)
        t1 = time.perf_counter()
        for _ in range(args.calls):
            ker.update_p(beta, active, R, dinv, P1)
        t2 = time.perf_counter()
        for _ in range(args.calls):
            launch()
        t3 = time.perf_counter()
        us = [1e6 * (b - a) / args.calls for a, b in ((t0, t1), (t1, t2), (t2, t3))]
        print(f"{n} voxels x {lanes}: Taichi's path {us[0]:.1f} us, @ti.kernel call (short "
              f"path) {us[1]:.1f} us, bound launch {us[2]:.1f} us")
    print("same bytes:", np.array_equal(P0, P1) and np.array_equal(P1, P2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
