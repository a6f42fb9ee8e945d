"""Shared test set-up: Taichi on the CPU once per session; TINY_SCENE_SETS shrinks the default scene.

Taichi keeps its default offline cache (``~/.cache/taichi``), so a second test session does not
recompile the kernels.
"""

import pytest

#: ``--set`` overrides that shrink the built-in tabletop scene to a few-second run: 64x48 images
#: (the Kinect intrinsics of the 320x240 default scaled by 1/5), 6 views, 3 cm voxels with a
#: 6 cm observation truncation, and 5000 metric samples per surface; no plots.
TINY_SCENE_SETS = (
    "synthetic.width=64", "synthetic.height=48",
    "synthetic.fx=52.5", "synthetic.fy=52.5", "synthetic.cx=31.5", "synthetic.cy=23.5",
    "synthetic.n_views=6",
    "tsdf.voxel_size_m=0.03", "tsdf.trunc_m=0.06",
    "eval.n_samples=5000",
    "run.plots=false",  # tests/test_plots.py covers them
)


@pytest.fixture(scope="session", autouse=True)
def taichi_cpu():
    """Initialise Taichi on the CPU once for the whole session (idempotent)."""
    from bftaichi.backend import init

    init("cpu")


def solved(cfg, frames, *, variance=True):
    """A Reconstructor of ``cfg`` that fused ``frames`` and its posterior."""
    from bftaichi.reconstructor import Reconstructor

    recon = Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C, name=f.name)
    return recon, recon.solve(variance=variance)


def posterior_system(recon):
    """Steps 2-4 of ``recon``'s last solve again, by the stage functions: the band and the
    posterior's linear system (:class:`bftaichi.stages.prior.System`), for tests that need Q.
    It is the posterior's Q with the Gaussian curvature prior (``prior.curvature_scale = 0``);
    with the robust one, the default, it holds that prior at unit weights, not the weights nor
    the Hessian :func:`bftaichi.stages.solve.solve_map` leaves, so tests comparing against
    ``Q^-1`` pin the Gaussian prior."""
    from bftaichi.stages.band import build_band
    from bftaichi.stages.observe import make_observer, observe
    from bftaichi.stages.prior import add_prior

    cfg, post = recon.config, recon.posterior
    vs, tau = cfg.tsdf.voxel_size_m, cfg.tsdf.trunc_m
    band, _ = build_band(recon.voxels, cfg.tsdf.bootstrap_trunc_m)
    observer = make_observer(band, cfg.observation, vs, tau, post.sigma_extra_m,
                             post.sigma_corr_m)
    S, h, _ = observe(observer, recon.frames, cfg.observation.stride)
    return band, add_prior(S, h, band, cfg.prior, cfg.band.stencil, vs)


def pulled_inside(S, nbr, far, mean, idx, trunc_m, voxel_size_m, strength=1000.0):
    """A strong pull of voxels ``idx`` to ``-trunc_m`` (``strength`` per voxel^2, as the
    samples that assert "inside" across an occlusion edge or behind a thin part pull them),
    added to the stencil ``S`` in place: returns ``h`` with the MAP ``mean`` of the unpulled
    system (``Q mean = h`` there) and the pulled MAP ``bent``."""
    import numpy as np
    from kernels.pcg import pcg
    from kernels.stencil import apply_Q

    h = apply_Q(S, nbr, mean, far=far).astype(np.float32)
    c = np.float32(strength / voxel_size_m ** 2)
    S[idx, 13] += c
    h[idx] += c * np.float32(-trunc_m)
    bent, _ = pcg(S, nbr, h, mean, tol=1e-8, maxiter=2000, far=far)
    return h, bent


def to_csr(S, nbr, far=None):
    """Q (N, N) scipy CSR float64 of a stencil ``S, nbr`` and its optional ``far`` part
    (:mod:`kernels.stencil`'s layout), for exact references on small problems."""
    import numpy as np
    import scipy.sparse as sp

    n = len(S)
    i, o = np.nonzero(nbr >= 0)
    Q = sp.csr_matrix((S[i, o].astype(np.float64), (i, nbr[i, o])), shape=(n, n))
    if far is not None:
        S2, nbr2 = far
        i, a = np.nonzero(nbr2 >= 0)
        Q = Q + sp.csr_matrix((S2[i, a].astype(np.float64), (i, nbr2[i, a])), shape=(n, n))
    return Q


def box_data_term(ijk, W):
    """Dense ``D = sum_i W_i E_i[a a^T]`` (x uniform in voxel i's box, a the trilinear weights
    of the cell holding x; cells with a corner outside the band dropped), integrated exactly:
    2-point Gauss-Legendre per axis on each half of the box (a a^T is quadratic per axis)."""
    import numpy as np

    corners = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    n = len(ijk)
    index = {v: k for k, v in enumerate(map(tuple, ijk.tolist()))}
    g = np.array([-1.0, 1.0]) / np.sqrt(3.0) * 0.25  # GL nodes on a half interval of length 1/2
    D = np.zeros((n, n))
    for i in np.flatnonzero(W > 0):
        for sh in corners:  # octant: t < 0 along the axes where sh = 1
            base = ijk[i] - sh
            cell = [index.get(tuple(base + c)) for c in corners]
            if None in cell:
                continue
            for q in corners:  # 8 quadrature points of the octant, weight 1/64 each
                t = np.where(sh == 1, -0.25, 0.25) + g[q]
                f = t + sh
                a = np.prod(np.where(corners == 1, f, 1 - f), axis=1)
                D[np.ix_(cell, cell)] += W[i] * np.outer(a, a) / 64.0
    return D
