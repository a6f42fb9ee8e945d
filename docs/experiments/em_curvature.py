"""The empirical-Bayes (EM) update of the curvature prior's strength on a suite case (issue 15;
measured, not built: docs/measurements.md, "Empirical Bayes for `prior.curvature`").

    python docs/experiments/em_curvature.py stanford-bunny sparse_far 0.1

The case of ``tools/suite.py`` is solved with ``prior.curvature = lam2`` and the plain
posterior variance (``solver.variance = posterior``, no prior bias, no local noise), so that
``var`` and ``cov`` are the probes' ``diag(Q^-1)`` and face covariances. The prior charges each
second difference ``d = x_(j-e) - 2 x_j + x_(j+e)`` along an axis ``e`` the precision
``lam2 / h^2``; the EM update of its strength (the marginal likelihood's fixed point) is

    lam2' = r h^2 / sum_d E[d^2 | data],   E[d^2 | data] = d(mu)^2 + Var(d),

over the ``r`` second differences whose three voxels are observed and within 1.5 voxels of the
mean's surface (the band's outer voxels are the clamped bootstrap, no SDF). ``Var(d)`` is
``var_(j-e) + 4 var_j + var_(j+e) - 4 cov_(j-e,j) - 4 cov_(j,j+e) + 2 cov_(j-e,j+e)``, the last
covariance (two voxels apart, which the probes do not keep) taken as
``cov_(j-e,j) cov_(j,j+e) / var_j``. Printed: the two parts of the mean ``E[d^2] / h^2`` and
``lam2'``; run again with ``lam2'`` to iterate.
"""
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tools"))
import checkout  # noqa: F401,E402  (this checkout's bftaichi first on sys.path)


def main(argv) -> int:
    import bftaichi as bf
    import suite
    from bftaichi.formats.synthetic import SyntheticDataset
    from kernels.probes import FACE_PLUS

    mesh, condition = argv[0], argv[1]
    lam2 = float(argv[2]) if len(argv) > 2 else 0.1
    cfg = bf.load_config(None, [*suite.case_sets(mesh, condition, ROOT.parent / "shared" / "data"),
                                "solver.variance=posterior", "solver.prior_bias=false",
                                "observation.local_noise=false", f"prior.curvature={lam2}"])
    frames = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
    recon = bf.Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    post = recon.solve()
    h = cfg.tsdf.voxel_size_m
    mu, var, cov = (np.asarray(a, np.float64) for a in (post.mean, post.var, post.cov))
    nbr = post.band.nbr
    near = (np.abs(mu) < 1.5 * h) & (post.band.weight > 0)
    r, d2, vd = 0, 0.0, 0.0
    for e, plus in enumerate(FACE_PLUS):
        jp, jm = nbr[:, plus], nbr[:, 26 - plus]
        j = np.flatnonzero((jp >= 0) & (jm >= 0))
        jp, jm = jp[j], jm[j]
        keep = near[j] & near[jp] & near[jm]
        j, jp, jm = j[keep], jp[keep], jm[keep]
        d = mu[jm] - 2 * mu[j] + mu[jp]
        c_m, c_p = cov[jm, e], cov[j, e]
        var_d = (var[jm] + 4 * var[j] + var[jp] - 4 * c_m - 4 * c_p
                 + 2 * c_m * c_p / np.maximum(var[j], 1e-30))
        r += len(j)
        d2 += float(np.sum(d * d))
        vd += float(np.sum(var_d))
    print(f"{mesh}/{condition}, prior.curvature = {lam2:g}: {r} second differences; mean "
          f"E[d^2] / h^2 = {d2 / r / h ** 2:.4f} (mean) + {vd / r / h ** 2:.4f} (variance); "
          f"EM update lam2' = {r * h * h / (d2 + vd):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
