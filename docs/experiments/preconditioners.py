"""Iteration counts of PCG on a real MAP system with other preconditioners (issue 16; measured,
not built: docs/measurements.md, "Preconditioners for the MAP and the probes").

    python docs/experiments/preconditioners.py dump /tmp/sys.npz fuse \\
        ../shared/data/rgbd/7scenes-redkitchen --voxel 0.02 --out /tmp/k2 -q
    python docs/experiments/preconditioners.py count /tmp/sys.npz /tmp/k2/band.npz

``dump`` runs a bftaichi command with the MAP's first PCG call saving its system (the stencil,
its far part, h and the warm start). ``count`` builds that Q in scipy and counts the
iterations of scipy's CG to 1e-6 from the warm start (the MAP) and to 1e-3 from zero on a
Rademacher right-hand side (a probe) with: Jacobi (the solver's), block Jacobi over 2 x 2 x 2
voxel aggregates, and a V-cycle over three levels of those aggregates (piecewise constant
prolongation, Galerkin coarse operators, one damped Jacobi sweep before and after, a direct
solve on the coarsest level).
"""
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def dump(path, argv):
    import kernels.pcg as P

    orig, calls = P.pcg, [0]

    def wrap(S, nbr, h, x0=None, tol=1e-6, maxiter=1000, far=None, compact=None):
        if calls[0] == 0:
            S2, nbr2 = far if far is not None else (0, 0)
            np.savez(path, S=np.asarray(S), nbr=np.asarray(nbr), h=np.asarray(h),
                     x0=np.asarray(x0), S2=np.asarray(S2), nbr2=np.asarray(nbr2))
        calls[0] += 1
        return orig(S, nbr, h, x0, tol, maxiter, far, compact)

    P.pcg = wrap
    from bftaichi.cli import main

    return main(argv)


def matrix(d):
    S, nbr = d["S"], d["nbr"]
    n = len(S)
    i, o = np.nonzero(nbr >= 0)
    Q = sp.csr_matrix((S[i, o].astype(np.float64), (i, nbr[i, o])), shape=(n, n))
    if d["S2"].ndim == 2:
        i, a = np.nonzero(d["nbr2"] >= 0)
        Q = Q + sp.csr_matrix((d["S2"][i, a].astype(np.float64), (i, d["nbr2"][i, a])),
                              shape=(n, n))
    return Q.tocsr()


def iterations(Q, b, x0, tol, apply_m):
    count = [0]

    def tick(_):
        count[0] += 1

    M = spla.LinearOperator(Q.shape, matvec=apply_m)
    spla.cg(Q, b, x0=x0.copy(), rtol=tol, M=M, callback=tick, maxiter=3000)
    return count[0]


def block_inverse(A, agg, n_agg):
    """The inverse of A's diagonal blocks over the aggregates (at most 8 voxels), sparse."""
    A = A.tocoo()
    keep = agg[A.row] == agg[A.col]
    order = np.argsort(agg, kind="stable")
    counts = np.bincount(agg, minlength=n_agg)
    pos = np.empty(len(agg), np.int64)
    pos[order] = np.arange(len(agg)) - np.repeat(np.cumsum(counts) - counts, counts)
    B = np.zeros((n_agg, 8, 8))
    B[agg[A.row[keep]], pos[A.row[keep]], pos[A.col[keep]]] = A.data[keep]
    for k in range(8):
        B[counts <= k, k, k] = 1.0
    inv = np.linalg.inv(B)
    member = np.full((n_agg, 8), -1)
    member[agg[order], pos[order]] = order
    r, c = np.nonzero(np.ones((8, 8)))
    R, C, V = member[:, r], member[:, c], inv[:, r, c]
    ok = (R >= 0) & (C >= 0)
    return sp.csr_matrix((V[ok], (R[ok], C[ok])), shape=A.shape)


def count(sys_path, band_path):
    d = np.load(sys_path)
    ijk = np.load(band_path)["ijk"].astype(np.int64)
    Q = matrix(d)
    n = Q.shape[0]
    h, x0 = d["h"].astype(np.float64), d["x0"].astype(np.float64)
    probe = np.random.default_rng(0).choice([-1.0, 1.0], n)
    levels, A, c = [], Q, ijk
    for _ in range(3):
        u, agg = np.unique(c // 2, axis=0, return_inverse=True)
        agg = agg.ravel()
        P = sp.csr_matrix((np.ones(A.shape[0]), (np.arange(A.shape[0]), agg)),
                          shape=(A.shape[0], len(u)))
        levels.append(dict(A=A, P=P, dinv=1.0 / A.diagonal(), binv=block_inverse(A, agg, len(u))))
        A, c = (P.T @ A @ P).tocsr(), u
    coarse = spla.splu(A.tocsc())

    def vcycle(b, level=0):
        if level == len(levels):
            return coarse.solve(b)
        lv = levels[level]
        x = 0.7 * lv["dinv"] * b
        x = x + lv["P"] @ vcycle(lv["P"].T @ (b - lv["A"] @ x), level + 1)
        return x + 0.7 * lv["dinv"] * (b - lv["A"] @ x)

    dinv = 1.0 / Q.diagonal()
    for name, m in (("Jacobi", lambda r: dinv * r), ("block Jacobi 2^3", lambda r: levels[0]["binv"] @ r),
                    ("V-cycle, 3 levels", vcycle)):
        print(f"{name}: MAP {iterations(Q, h, x0, 1e-6, m)} iterations, probe "
              f"{iterations(Q, probe, np.zeros(n), 1e-3, m)}", flush=True)


if __name__ == "__main__":
    if sys.argv[1] == "dump":
        sys.exit(dump(sys.argv[2], sys.argv[3:]))
    count(sys.argv[2], sys.argv[3])
