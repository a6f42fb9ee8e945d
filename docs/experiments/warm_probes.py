"""Potential of warm-started probes in a scan step (issue 18; docs/measurements.md, "Two
scan-step leads that found nothing"): the probe signs keyed by voxel (a hash of its ijk) instead
of by row, and the previous solve's probe solutions, mapped by ijk, as the start of the next
solve after one more view is fused. Prints the probes' PCG iterations cold and warm::

    python docs/experiments/warm_probes.py scenes/bowl.toml
    python docs/experiments/warm_probes.py scenes/clutter.toml
"""
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
import numpy as np
import bftaichi as bf
import kernels.probes as kp
from bftaichi.planning.scan import _Scene

STATE = {"ijk": None, "U": None, "warm": False, "log": []}
orig_vectors, orig_pcg = kp.probe_vectors, kp.pcg_batched

def hashed_vectors(n, n_probes, seed=0, *, method, ijk=None):
    Z = orig_vectors(n, n_probes, seed, method=method, ijk=ijk)  # colouring mask * signs
    key = (ijk[:, 0].astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
           ^ ijk[:, 1].astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
           ^ ijk[:, 2].astype(np.uint64) * np.uint64(0x165667B19E3779F9)
           ^ np.uint64(seed + 1) * np.uint64(0x27D4EB2F165667C5))
    key ^= key >> np.uint64(31); key *= np.uint64(0xBF58476D1CE4E5B9); key ^= key >> np.uint64(29)
    bits = (key[:, None] >> np.arange(n_probes, dtype=np.uint64)[None, :]) & np.uint64(1)
    signs = (2.0 * bits - 1.0).astype(np.float32)
    STATE["cur_ijk"] = np.asarray(ijk)
    return (np.abs(Z) * signs).astype(np.float32)

def pcg_spy(S, nbr, B, X0=None, tol=1e-6, maxiter=1000, dtype=np.float32, check=True, far=None,
            compact=None):
    if B.shape[1] > 1 and STATE["warm"] and STATE["U"] is not None:
        ijk = STATE["cur_ijk"]
        from bftaichi.posterior import warm_start
        zero = np.zeros(len(ijk), np.float32)
        X0 = np.stack([warm_start(STATE["ijk"], STATE["U"][:, k], ijk, zero)
                       for k in range(B.shape[1])], axis=1).astype(np.float32)
    X, info = orig_pcg(S, nbr, B, X0, tol, maxiter, dtype, check, far, compact)
    if B.shape[1] > 1:
        STATE["log"].append(list(info["iterations"]))
        STATE["ijk"], STATE["U"] = STATE["cur_ijk"].copy(), X.copy()
    return X, info

kp.probe_vectors, kp.pcg_batched = hashed_vectors, pcg_spy
cfg = bf.load_config(sys.argv[1], [])
sc = _Scene(cfg)
recon = bf.Reconstructor(cfg)
views = sc.initial + [c for c in range(len(sc.poses)) if c not in sc.initial][:7]
for c in views[:-1]:
    f = sc.frame(c); recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
recon.solve(variance=True)
f = sc.frame(views[-1]); recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
saved = (STATE["ijk"], STATE["U"])
for warm in (False, True):
    STATE["warm"] = warm; STATE["ijk"], STATE["U"] = saved
    t0 = time.perf_counter(); post = recon.solve(variance=True); t = time.perf_counter() - t0
    print(f"{sys.argv[1]} warm={warm}: probe iterations {STATE['log'][-1]}, "
          f"variance {post.seconds['variance']:.3f} s, solve {t:.2f} s")
