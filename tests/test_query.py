"""``Posterior.query`` and ``Posterior.to_dense`` (issue 19, item 4) against numpy references
built from the band's voxel coordinates: the trilinear mean and variance over the cell of voxel
centres, its analytic gradient, the observed test (all 8 corners observed band voxels), and a
dense box filled voxel by voxel."""

import numpy as np
import pytest

import bftaichi as bf
from conftest import TINY_SCENE_SETS


@pytest.fixture(scope="module")
def post():
    from bftaichi.formats.synthetic import SyntheticDataset

    cfg = bf.load_config(None, TINY_SCENE_SETS)
    frames = SyntheticDataset(cfg.synthetic, cfg.scene.depth_min_m, cfg.scene.depth_max_m)
    recon = bf.Reconstructor(cfg)
    for f in frames:
        recon.integrate(f.depth_m, f.K, f.T_W_C)
    return recon.solve(variance=False)


def reference_query(post, points_W):
    """Trilinear mean / std / normalised gradient by a dict of voxel coordinates."""
    index = {tuple(v): k for k, v in enumerate(post.ijk.tolist())}
    seen = post.weight > 0
    vs = post.voxel_size
    out = []
    for p in points_W:
        if not np.isfinite(p).all():
            out.append(None)
            continue
        g = (p - post.origin) / vs - 0.5
        c0 = np.floor(g).astype(int)
        f = g - c0
        d = s = 0.0
        n = np.zeros(3)
        ok = True
        for c in np.ndindex(2, 2, 2):
            k = index.get(tuple(c0 + c))
            if k is None or not seen[k]:
                ok = False
                break
            w = np.prod([f[a] if c[a] else 1 - f[a] for a in range(3)])
            dw = [np.prod([(1 if c[b] else -1) if b == a else (f[b] if c[b] else 1 - f[b])
                           for b in range(3)]) for a in range(3)]
            d += w * post.mean[k]
            s += w * post.var[k]
            n += np.array(dw) * post.mean[k]
        out.append((d, n / np.linalg.norm(n), np.sqrt(s)) if ok else None)
    return out


def test_query_matches_the_trilinear_reference_in_world_coordinates(post):
    rng = np.random.default_rng(0)
    seen = post.ijk[post.weight > 0]
    centres = post.origin + (seen + 0.5) * post.voxel_size
    pts = centres[rng.integers(0, len(centres), 400)] + rng.uniform(-1, 1, (400, 3)) * \
        post.voxel_size
    pts = np.vstack([pts, [[1e4, 0, 0], [np.nan, 0, 0]]])
    sdf, grad, sigma, observed = post.query(pts)
    assert sdf.shape == sigma.shape == observed.shape == (402,) and grad.shape == (402, 3)
    ref = reference_query(post, pts)
    assert [r is not None for r in ref] == observed.tolist()
    assert 50 < observed.sum() < 400  # both kinds of point were drawn
    for i, r in enumerate(ref):
        if r is None:
            assert np.isnan(sdf[i]) and np.isnan(sigma[i]) and not grad[i].any()
            continue
        d, n, s = r
        assert abs(sdf[i] - d) <= 1e-6 + 1e-5 * abs(d)
        assert abs(sigma[i] - s) <= 1e-6 + 1e-5 * s
        np.testing.assert_allclose(grad[i], n, atol=1e-5)
    one = post.query(pts[0])  # a single point as a 3-vector
    assert one[0].shape == (1,) and (one[0][0] == sdf[0] or np.isnan(sdf[0]))
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        post.query(np.zeros((4, 2)))


def test_to_dense_holds_each_observed_voxel_of_the_box_and_nan_elsewhere(post):
    vs = post.voxel_size
    centres = post.origin + (post.ijk + 0.5) * vs
    lo = np.percentile(centres, 20, axis=0)
    hi = np.percentile(centres, 70, axis=0)
    dense = post.to_dense(lo, hi)
    sdf, sigma, o = dense["sdf"], dense["sigma"], dense["origin_W"]
    assert sdf.shape == sigma.shape and min(sdf.shape) > 1
    # every grid centre lies in the box, and one more step would leave it
    assert (o >= lo - 1e-9).all() and (o - vs < lo).all()
    top = o + (np.array(sdf.shape) - 1) * vs
    assert (top <= hi + 1e-9).all() and (top + vs > hi).all()
    expected = np.full(sdf.shape, np.nan, np.float32)
    expected_s = np.full(sdf.shape, np.nan, np.float32)
    for k in np.flatnonzero(post.weight > 0):
        a = np.rint((centres[k] - o) / vs).astype(int)
        if ((a >= 0) & (a < sdf.shape)).all():
            expected[tuple(a)] = post.mean[k]
            expected_s[tuple(a)] = np.sqrt(post.var[k])
    np.testing.assert_array_equal(sdf, expected)
    np.testing.assert_allclose(sigma, expected_s, rtol=1e-6)
    assert np.isfinite(sdf).sum() > 10 and np.isnan(sdf).sum() > 10
    with pytest.raises(ValueError, match="below"):
        post.to_dense(hi, lo)
