"""kernels.observe: the data term of the posterior against independent numpy/scipy references.

Small bands (voxel shells around a sphere and a box, 3 cm voxels) and tiny noiseless synthetic
frames (40x30 px). The references rebuild what DESIGN.md section 3 (steps 3-4) specifies from the
raw observation rows (``Observer.frame_rows``) or from the scene geometry: A^T W A and A^T W y as
scipy CSR products, the sample points from the pixel rays, the signed distance to the true box
face, the noise model from the true face normal, the accepted/dropped split from a dense
occupancy grid.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from bftaichi.config import SyntheticConfig
from bftaichi.formats.synthetic import SyntheticDataset
from kernels.lookup import build_block_table
from kernels.dataterm import MISFIT_NEAR
from kernels.layout import stencil_offset
from kernels.observe import Observer

VOXEL = 0.03
TRUNC = 2 * VOXEL
R_OBJ = 0.3  # sphere radius / box half extent, metres
NOISE = dict(depth_a_m=0.0012, depth_b=0.0019, depth_z0_m=0.4, cos_min=0.5, sigma_pose_m=0.002,
             sigma_model_m=0.001)
OFFSETS = np.array([stencil_offset(o) for o in range(27)])


def frames_of(mesh: str):
    cfg = SyntheticConfig(mesh=mesh, radius_m=R_OBJ, width=40, height=30, fx=50.0, fy=50.0,
                          cx=19.5, cy=14.5, noise="none", quantization_m=0.0, n_views=3,
                          trajectory="ring", cam_radius_m=1.2, cam_height_m=0.7)
    return list(SyntheticDataset(cfg))


def shell(sdf, half_width_vox: float) -> np.ndarray:
    """Voxels (lexicographic ijk, int32) whose centre has |sdf| < half_width_vox voxels."""
    r = np.arange(-16, 16)
    ijk = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    return ijk[np.abs(sdf((ijk + 0.5) * VOXEL)) < half_width_vox * VOXEL].astype(np.int32)


def sphere_sdf(x):
    return np.linalg.norm(x, axis=-1) - R_OBJ


def box_sdf(x):
    q = np.abs(x) - R_OBJ
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)


class Band:
    """A band, its lookup, a dense occupancy grid and the numpy-built 27-neighbour table."""

    def __init__(self, ijk):
        self.ijk = ijk
        self.keys, self.table = build_block_table(ijk)
        self.lo = ijk.min(axis=0) - 2
        shape = ijk.max(axis=0) - self.lo + 3
        self.grid = np.full(shape, -1, np.int64)
        self.grid[tuple((ijk - self.lo).T)] = np.arange(len(ijk))
        self.nbr = self.index_of(ijk[:, None, :] + OFFSETS[None])  # (N, 27)

    def index_of(self, ijk):
        g = np.asarray(ijk) - self.lo
        inside = ((g >= 0) & (g < self.grid.shape)).all(axis=-1)
        out = np.full(g.shape[:-1], -1, np.int64)
        out[inside] = self.grid[tuple(g[inside].T)]
        return out

    def observer(self, **kw):
        # the Observer's former defaults: count each pixel once, samples tau in front, no gate
        old = dict(count_once="pixel", front_m=TRUNC, gate_m=0.0)
        return Observer(self.keys, self.table, len(self.ijk), VOXEL, TRUNC,
                        **{**NOISE, **old, **kw})


@pytest.fixture(scope="module")
def sphere():
    return Band(shell(sphere_sdf, 2.5)), frames_of("sphere")


@pytest.fixture(scope="module")
def box():
    return Band(shell(box_sdf, 2.5)), frames_of("box")


def rays_W(frame):
    """World ray directions R_WC K^-1 (u, v, 1) (H, W, 3) and the camera centre."""
    H, W = frame.depth_m.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    K = frame.K
    d_C = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return d_C @ frame.T_W_C[:3, :3].T, frame.T_W_C[:3, 3]


def sample_points(frame, pixel, z):
    ray, cam = rays_W(frame)
    return cam + z[:, None] * ray.reshape(-1, 3)[pixel]


def box_faces(frame):
    """Per pixel: the box face (0..5 = axis * 2 + (positive side)) its surface point lies on, -1
    if invalid; and a mask of pixels whose 4 neighbours lie on the same face (flat stencil)."""
    ray, cam = rays_W(frame)
    p = cam + frame.depth_m[..., None].astype(np.float64) * ray
    axis = np.abs(p).argmax(-1)
    positive = np.take_along_axis(p, axis[..., None], -1)[..., 0] > 0
    face = np.where(frame.depth_m > 0, axis * 2 + positive, -1)
    flat = face >= 0
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        nb = np.full_like(face, -2)
        H, W = face.shape
        nb[max(dv, 0):H + min(dv, 0), max(du, 0):W + min(du, 0)] = \
            face[max(-dv, 0):H + min(-dv, 0), max(-du, 0):W + min(-du, 0)]
        flat &= nb == face
    return face, flat


def face_normal(face):
    n = np.zeros(face.shape + (3,))
    ok = face >= 0
    n[ok, face[ok] // 2] = np.where(face[ok] % 2 == 1, 1.0, -1.0)
    return n


def test_one_frame_moves_no_entry_beyond_its_growth_bound(sphere):
    """The adds test nothing for overflow: kernels.fixedpoint.growth_bound must bound what one
    frame adds to any accumulator entry (S and h, every part), else an entry could wrap
    around between two saturation counts."""
    from kernels.fixedpoint import growth_bound

    band, frames = sphere
    obs = band.observer()
    for frame in frames:
        before = obs.acc.copy()
        obs.integrate(frame.depth_m, frame.K, frame.T_W_C)
        moved = np.abs(obs.acc - before).max()
        (fx, fy), (cx, cy) = np.diag(frame.K)[:2], frame.K[:2, 2]
        assert 0 < moved <= growth_bound(frame.depth_m.shape, fx, fy, cx, cy, obs.spacing_m,
                                         obs.share, obs.m, obs.mf)


def test_saturated_entries_are_counted_before_they_can_wrap(sphere, monkeypatch):
    """An entry beyond 2^60 is reported: by the count integrate runs when the frames' summed
    growth bounds would pass GROWTH_LIMIT, by finalize, and not otherwise (no count runs)."""
    import kernels.observe as observe

    band, frames = sphere
    f = frames[0]
    obs = band.observer()
    assert obs.integrate(f.depth_m, f.K, f.T_W_C)["saturated"] == 0
    obs.acc[0, 3, 14] = -(1 << 60) - 1  # an entry of A^T W y
    obs.acc[-1, 7, 2] = (1 << 60) + 1  # one of the stencil
    assert obs.integrate(f.depth_m, f.K, f.T_W_C)["saturated"] == 0  # far from the limit
    monkeypatch.setattr(observe, "GROWTH_LIMIT", 1.25 * obs._unchecked)  # 2 frames in, 3rd passes
    assert obs.integrate(f.depth_m, f.K, f.T_W_C)["saturated"] == 2  # the count ran first
    assert obs.finalize()[2]["saturated"] == 2
    obs.reset()
    obs.integrate(f.depth_m, f.K, f.T_W_C)
    assert obs.finalize()[2]["saturated"] == 0


def stencil_matrix(S, nbr):
    N = len(S)
    keep = nbr >= 0
    rows = np.broadcast_to(np.arange(N)[:, None], nbr.shape)
    return sp.csr_matrix((S[keep].astype(np.float64), (rows[keep], nbr[keep])), shape=(N, N))


# -- tests ------------------------------------------------------------------------------------

def test_stencil_equals_csr_assembled_from_the_rows(sphere):
    """(a) The accumulated stencil is A^T W A and h is A^T W y (A, W, y from frame_rows, scipy
    CSR), over 3 frames at strides 1, 2, 1; the stencil is exactly symmetric and empty towards
    voxels outside the band."""
    band, frames = sphere
    obs = band.observer()
    rows = []
    for frame, stride in zip(frames, (1, 2, 1)):
        obs.integrate(frame.depth_m, frame.K, frame.T_W_C, stride=stride)
        rows.append(obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C, stride=stride))
    S, h, stats = obs.finalize()
    idx = np.concatenate([r["idx"] for r in rows])
    a = np.concatenate([r["a"] for r in rows])
    w = np.concatenate([r["w"] for r in rows])
    y = np.concatenate([r["y"] for r in rows])
    R, N = len(idx), len(band.ijk)
    assert stats["samples_accepted"] == R > 1000 and stats["saturated"] == 0
    A = sp.csr_matrix((a.ravel(), (np.repeat(np.arange(R), 8), idx.ravel())), shape=(R, N))
    Q_ref = (A.T @ sp.diags(w) @ A).tocsr()
    h_ref = A.T @ (w * y)
    Q = stencil_matrix(S, band.nbr)
    assert sp.linalg.norm(Q - Q_ref) / sp.linalg.norm(Q_ref) < 1e-5
    x = np.random.default_rng(0).standard_normal(N)
    assert np.linalg.norm(Q @ x - Q_ref @ x) / np.linalg.norm(Q_ref @ x) < 1e-5
    assert np.linalg.norm(h - h_ref) / np.linalg.norm(h_ref) < 1e-5
    assert (S[band.nbr < 0] == 0).all()
    i, o = np.nonzero(band.nbr >= 0)
    np.testing.assert_array_equal(S[i, o], S[band.nbr[i, o], 26 - o])


def test_rows_interpolate_the_sample_points(sphere):
    """Each row's 8 corners are the cell around its sample point x = t + z R K^-1 (u, v, 1):
    the weights sum to 1 and interpolate the voxel centres (ijk + 0.5) * voxel to x."""
    band, frames = sphere
    obs = band.observer()
    for frame in frames:
        r = obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        x = sample_points(frame, r["pixel"], r["z"])
        centres = (band.ijk[r["idx"]] + 0.5) * VOXEL  # (R, 8, 3)
        np.testing.assert_allclose(r["a"].sum(1), 1.0, atol=1e-12)
        assert (r["a"] >= 0).all()
        np.testing.assert_allclose(np.einsum("rc,rcx->rx", r["a"], centres), x, atol=1e-9)
        # the cell is the one around x (no corner further than one voxel on any axis)
        assert (np.abs(centres - x[:, None]) <= VOXEL * (1 + 1e-9)).all()


def test_plane_observations_are_signed_distances(box):
    """(b) On a flat box face, y of every sample is its signed distance to the face plane
    (positive in front), exact up to float32 depth rounding."""
    band, frames = box
    obs = band.observer()
    n_checked = 0
    for frame in frames:
        face, flat = box_faces(frame)
        r = obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        sel = flat.ravel()[r["pixel"]]
        f = face.ravel()[r["pixel"][sel]]
        x = sample_points(frame, r["pixel"][sel], r["z"][sel])
        sdf = np.where(f % 2 == 1, 1.0, -1.0) * x[np.arange(len(f)), f // 2] - R_OBJ
        np.testing.assert_allclose(r["y"][sel], sdf, atol=1e-6)
        assert (np.abs(sdf) > VOXEL).any()  # samples away from the surface are included
        n_checked += sel.sum()
    assert n_checked > 300


def test_front_samples_reach_front_m_in_front_only(box):
    """front_m = 2 tau: a pixel's samples run from D - 2 tau to D + tau (camera depth), and
    those in front still observe their signed distance to the face plane."""
    band, frames = box
    near, far = band.observer(), band.observer(front_m=2 * TRUNC)
    frame = frames[0]
    face, flat = box_faces(frame)
    r_near = near.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
    r_far = far.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
    D = frame.depth_m.ravel()
    dz_near = r_near["z"] - D[r_near["pixel"]]
    dz_far = r_far["z"] - D[r_far["pixel"]]
    assert dz_near.min() >= -TRUNC - 1e-9 and dz_near.max() <= TRUNC + 1e-9
    assert dz_far.min() < -1.5 * TRUNC and dz_far.min() >= -2 * TRUNC - 1e-9
    assert dz_far.max() <= TRUNC + 1e-9  # behind the surface: still tau
    sel = flat.ravel()[r_far["pixel"]]
    f = face.ravel()[r_far["pixel"][sel]]
    x = sample_points(frame, r_far["pixel"][sel], r_far["z"][sel])
    sdf = np.where(f % 2 == 1, 1.0, -1.0) * x[np.arange(len(f)), f // 2] - R_OBJ
    np.testing.assert_allclose(r_far["y"][sel], sdf, atol=1e-6)
    with pytest.raises(ValueError, match="front_m"):
        band.observer(front_m=0.5 * TRUNC)


def test_samples_behind_the_surface_reach_tau_times_the_incidence_cosine(box):
    """With behind_incidence, a pixel's samples behind the surface reach at most tau
    max(cos(angle), cos_min) in camera depth (kernels.observe, step 2b): a ray at a grazing
    angle leaves the body soon after it enters, so its samples stop asserting "inside" sooner;
    head-on rays reach on. Without it they reach tau (the paper's +-tau)."""
    band, frames = box
    obs, paper = band.observer(behind_incidence=True), band.observer()
    cos_min = NOISE["cos_min"]
    reach_head_on, n_grazing = 0.0, 0
    for frame in frames:
        face, flat = box_faces(frame)
        r = obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        ray, _ = rays_W(frame)
        ray = ray.reshape(-1, 3)[r["pixel"]]
        n = face_normal(face).reshape(-1, 3)[r["pixel"]]
        cos = np.abs(np.einsum("ij,ij->i", n, ray)) / np.linalg.norm(ray, axis=1)
        behind = flat.ravel()[r["pixel"]] & (r["z"] > frame.depth_m.ravel()[r["pixel"]])
        dz = (r["z"] - frame.depth_m.ravel()[r["pixel"]])[behind]
        assert (dz <= TRUNC * np.maximum(cos[behind], cos_min) + 1e-6).all()
        reach_head_on = max(reach_head_on, dz[cos[behind] > 0.9].max(initial=0.0))
        n_grazing += int((cos[behind] < 0.45).sum())
        # the default (the paper's +-tau) reaches tau behind whatever the angle
        p = paper.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        dz_paper = p["z"] - frame.depth_m.ravel()[p["pixel"]]
        assert dz_paper.max() == pytest.approx(TRUNC, abs=1e-6) and len(p["z"]) > len(r["z"])
    assert reach_head_on >= 0.5 * TRUNC - 1e-6  # head-on rays keep samples behind
    assert n_grazing > 0  # ... and so do grazing ones, down to the floor cos_min


def test_plane_normals_face_the_camera(box):
    """(c) Normals of flat box-face pixels are the face's outward normal (which faces the
    camera); every normal is a unit vector facing the camera; an isolated pixel falls back to
    the negated ray direction."""
    band, frames = box
    obs = band.observer()
    for frame in frames:
        face, flat = box_faces(frame)
        n, fallback = obs.frame_normals(frame.depth_m, frame.K, frame.T_W_C)
        ray, _ = rays_W(frame)
        valid = frame.depth_m > 0
        assert flat.sum() > 100
        np.testing.assert_allclose(n[flat], face_normal(face)[flat], atol=2e-5)
        np.testing.assert_allclose(np.linalg.norm(n[valid], axis=-1), 1.0, atol=1e-5)
        assert ((n[valid] * ray[valid]).sum(-1) < 0).all()
        assert not fallback[flat].any()
    frame = frames[0]
    lone = np.zeros_like(frame.depth_m)
    lone[10, 25] = 1.3
    lone[20, 5] = 1.3  # plus a pixel whose neighbours are all 1 m away (a depth jump)
    lone[19:22, 4:7][[0, 1, 1, 2], [1, 0, 2, 1]] = 0.3
    n, fallback = obs.frame_normals(lone, frame.K, frame.T_W_C)
    ray, _ = rays_W(frame)
    for v, u in ((10, 25), (20, 5)):
        assert fallback[v, u]
        np.testing.assert_allclose(n[v, u], -ray[v, u] / np.linalg.norm(ray[v, u]), atol=1e-6)


def test_noisy_pixels_take_the_normal_baseline_their_noise_needs(box):
    """With ``normal_max_noise_rad`` each pixel's normal reads the neighbours r pixels away,
    r the smallest (at most ``normal_radius_px``) with hypot(a + b (D - z0)^2, sigma_axial) fx
    / (sqrt(2) r D) <= the limit: exactly the normal of a fixed-r Observer there; on a noisy
    tilted plane those normals are much closer to the plane's than the 1-pixel ones."""
    band, _ = box
    H, W, f = 60, 80, 60.0
    K = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    v, u = np.mgrid[0:H, 0:W]
    ray = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones((H, W))], -1)
    n_true = np.array([np.sin(0.5), 0.0, -np.cos(0.5)])  # tilted 0.5 rad, facing the camera
    depth = np.cos(0.5) / (ray @ -n_true)  # the plane through (0, 0, 1): 0.73-1.56 m
    axial = 0.02
    noisy = (depth + np.random.default_rng(0).normal(0.0, axial, depth.shape)).astype(np.float32)
    T = np.eye(4)
    limit, r_max = 0.6, 4
    fixed = {r: band.observer(sigma_axial_m=axial, normal_radius_px=r).frame_normals(
        noisy, K, T)[0] for r in range(1, r_max + 1)}
    n_rule, _ = band.observer(sigma_axial_m=axial, normal_radius_px=r_max,
                              normal_max_noise_rad=limit).frame_normals(noisy, K, T)
    a, b, z0 = NOISE["depth_a_m"], NOISE["depth_b"], NOISE["depth_z0_m"]
    D = noisy.astype(np.float64)
    r = np.clip(np.ceil(np.hypot(a + b * (D - z0) ** 2, axial) * f / (np.sqrt(2) * D * limit)),
                1, r_max).astype(int)
    assert len(np.unique(r)) >= 2  # the depth range spans more than one baseline
    for k in np.unique(r):
        np.testing.assert_array_equal(n_rule[r == k], fixed[k][r == k])
    inner = (slice(r_max, H - r_max), slice(r_max, W - r_max))
    angle = {name: np.degrees(np.arccos(np.clip(n[inner] @ n_true, -1, 1))).mean()
             for name, n in (("rule", n_rule), ("one", fixed[1]))}
    assert angle["rule"] < 0.7 * angle["one"], angle  # measured 24.5 against 39.3 degrees


@pytest.mark.parametrize("axial", [0.0, 0.004])
def test_each_pixel_counts_its_information_once(box, axial):
    """(d) Per pixel, the weights of its accepted samples are equal and sum to 1 / sigma^2,
    sigma^2 = (sqrt((a + b (D - z0)^2)^2 + sigma_axial^2) max(cos, cos_min) |ray|)^2 +
    sigma_pose^2 + sigma_model^2 with the true face normal and ray = K^-1 (u, v, 1) (y = (z - D)
    <n, ray>): extra depth noise along the ray (``sigma_axial_m``) moves y as the sensor's does;
    summed over the stencil, S holds exactly sum over pixels of 1 / sigma^2."""
    band, frames = box
    obs = band.observer(sigma_axial_m=axial)
    total_info = 0.0
    for frame in frames:
        face, flat = box_faces(frame)
        r = obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        obs.integrate(frame.depth_m, frame.K, frame.T_W_C)
        pix, n_acc = np.unique(r["pixel"], return_counts=True)
        info = np.bincount(r["pixel"], weights=r["w"], minlength=flat.size)[pix]
        of_row = np.searchsorted(pix, r["pixel"])
        np.testing.assert_allclose(r["w"] * n_acc[of_row], info[of_row], rtol=1e-12)  # equal w
        assert len(set(n_acc.tolist())) > 1  # pixels with different sample counts
        total_info += info.sum()
        ray, _ = rays_W(frame)
        ray = ray.reshape(-1, 3)[pix]
        D = frame.depth_m.ravel()[pix].astype(np.float64)
        cos = -(face_normal(face).reshape(-1, 3)[pix] * ray).sum(-1) / np.linalg.norm(ray, axis=-1)
        a, b, z0, cmin = (NOISE[k] for k in ("depth_a_m", "depth_b", "depth_z0_m", "cos_min"))
        sd = np.hypot(a + b * (D - z0) ** 2, axial) * np.maximum(cos, cmin) * \
            np.linalg.norm(ray, axis=-1)
        var = sd ** 2 + NOISE["sigma_pose_m"] ** 2 + NOISE["sigma_model_m"] ** 2
        on_face = flat.ravel()[pix]
        assert on_face.sum() > 100 and (cos[on_face] < cmin).any() and (cos[on_face] > cmin).any()
        np.testing.assert_allclose(info[on_face], 1.0 / var[on_face], rtol=1e-4)
    S, _, _ = obs.finalize()
    # sum_{i,o} S[i, o] = sum_k w_k (sum_c a_c)^2 = sum_k w_k = sum_pixels 1 / sigma^2
    np.testing.assert_allclose(S.astype(np.float64).sum(), total_info, rtol=1e-5)


def test_count_once_per_voxel_gives_each_voxel_at_most_one_pixel(box):
    """count_once="voxel" at 1-voxel spacing: every sample carries its pixel's whole 1/sigma^2
    (w_voxel / w_pixel = n_acc, rows and values unchanged), and still no voxel gets more than
    about one pixel's information from a pixel: sum_k w_k a_k^2 <= sum_k w_k a_k ~ 1/sigma^2,
    because the trilinear weights a ray's samples put on one voxel sum to about 1 at most."""
    band, frames = box
    frame = frames[0]
    per_pixel = band.observer().frame_rows(frame.depth_m, frame.K, frame.T_W_C)
    per_voxel = band.observer(count_once="voxel").frame_rows(frame.depth_m, frame.K, frame.T_W_C)
    np.testing.assert_array_equal(per_voxel["idx"], per_pixel["idx"])
    np.testing.assert_array_equal(per_voxel["y"], per_pixel["y"])
    _, inverse, n_acc = np.unique(per_pixel["pixel"], return_inverse=True, return_counts=True)
    n = n_acc[inverse].astype(np.float64)
    assert (n > 2).any()
    np.testing.assert_allclose(per_voxel["w"] / per_pixel["w"], n, rtol=1e-12)
    # per (pixel, voxel): the weights its samples put there, and the information they carry
    pair = per_voxel["pixel"][:, None] * (int(per_voxel["idx"].max()) + 1) + per_voxel["idx"]
    keys, at = np.unique(pair.ravel(), return_inverse=True)
    a = per_voxel["a"].ravel()
    sum_a = np.bincount(at, weights=a, minlength=len(keys))
    info = np.bincount(at, weights=(per_voxel["w"][:, None] * per_voxel["a"] ** 2).ravel(),
                       minlength=len(keys))
    inv_var = np.zeros(len(keys))
    np.maximum.at(inv_var, at, np.repeat(per_voxel["w"], 8))
    # samples of an oblique ray (1 voxel apart in camera z) sum the hat to 1 up to a few %
    assert 0.9 < sum_a.max() <= 1.05
    assert (info <= 1.05 * inv_var).all()


def test_accumulation_is_deterministic_and_order_free(sphere):
    """(e) The same frames give bitwise identical S and h, run twice or in reverse order."""
    band, frames = sphere
    results = []
    for order in (frames, frames, frames[::-1]):
        obs = band.observer()
        for frame in order:
            obs.integrate(frame.depth_m, frame.K, frame.T_W_C)
        results.append(obs.finalize())
    for S, h, stats in results[1:]:
        np.testing.assert_array_equal(S, results[0][0])
        np.testing.assert_array_equal(h, results[0][1])
        assert stats == results[0][2]
    assert np.abs(results[0][1]).max() > 0


def test_samples_whose_cell_leaves_the_band_are_dropped(sphere):
    """(f) With a band thinner than +-tau, exactly the samples whose cell has a corner outside
    the band (dense-grid reference) are dropped, and they are counted."""
    band_full, frames = sphere
    band = Band(shell(sphere_sdf, 1.2))
    obs = band.observer()
    for frame, stride in zip(frames, (1, 2)):
        r = obs.frame_rows(frame.depth_m, frame.K, frame.T_W_C, stride=stride)
        counts = obs.integrate(frame.depth_m, frame.K, frame.T_W_C, stride=stride)
        assert counts == r["counts"]
        H, W = frame.depth_m.shape
        v, u = np.mgrid[0:H:stride, 0:W:stride]
        pixel = (v * W + u).ravel()
        pixel = pixel[frame.depth_m.ravel()[pixel] > 0]
        m = int(round(TRUNC / VOXEL))
        z = (frame.depth_m.ravel()[pixel].astype(np.float64)[:, None]
             + np.arange(-m, m + 1) * VOXEL).ravel()
        pixel = np.repeat(pixel, 2 * m + 1)
        c0 = np.floor(sample_points(frame, pixel, z) / VOXEL - 0.5).astype(np.int64)
        corners = c0[:, None] + np.array([[c >> 2, (c >> 1) & 1, c & 1] for c in range(8)])
        inside = (band.index_of(corners) >= 0).all(axis=1)
        assert (~inside).sum() > 0 and inside.sum() > 0
        assert counts["samples_dropped"] == (~inside).sum()
        assert counts["samples_accepted"] == inside.sum()
        got = set(zip(r["pixel"].tolist(), np.round(r["z"], 9).tolist()))
        assert got == set(zip(pixel[inside].tolist(), np.round(z[inside], 9).tolist()))
        assert (r["idx"] >= 0).all()
    _, _, stats = obs.finalize()
    assert stats["samples_dropped"] > 0 and stats["frames"] == 2


def test_side_gate_drops_exactly_the_samples_the_reference_contradicts(sphere):
    """(g) Side gate (step 3b): with the true SDF as reference nothing is gated; with a
    reference that calls one half-space free (+1 m) and the other inside (-1 m), exactly the
    ungated rows with ``y < 0, t > gate`` or ``y > 0, t < -gate`` (t: the reference
    interpolated by the row's own weights) are gated, counted, and the rest is unchanged; a
    NaN reference gates nothing."""
    band, frames = sphere
    gate = 0.5 * TRUNC
    true_ref = sphere_sdf((band.ijk + 0.5) * VOXEL).astype(np.float32)
    half = np.where(band.ijk[:, 0] >= 0, 1.0, -1.0).astype(np.float32)
    plain = band.observer()
    n_gated = 0
    for frame in frames:
        rows = plain.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        exact = band.observer(reference=true_ref, gate_m=gate)
        assert exact.integrate(frame.depth_m, frame.K, frame.T_W_C)["samples_gated"] == 0
        t = (rows["a"] * half[rows["idx"]]).sum(axis=1)
        contradicted = ((rows["y"] < 0) & (t > gate)) | ((rows["y"] > 0) & (t < -gate))
        gated = band.observer(reference=half, gate_m=gate)
        r = gated.frame_rows(frame.depth_m, frame.K, frame.T_W_C)
        assert r["counts"]["samples_gated"] == contradicted.sum()
        assert r["counts"]["samples_accepted"] == (~contradicted).sum()
        kept = set(zip(r["pixel"].tolist(), np.round(r["z"], 9).tolist()))
        assert kept == set(zip(rows["pixel"][~contradicted].tolist(),
                               np.round(rows["z"][~contradicted], 9).tolist()))
        n_gated += contradicted.sum()
        unknown = band.observer(reference=np.full(len(band.ijk), np.nan, np.float32),
                                gate_m=gate)
        assert unknown.integrate(frame.depth_m, frame.K, frame.T_W_C)["samples_gated"] == 0
    assert n_gated > 20
    with pytest.raises(ValueError, match="reference"):
        band.observer(gate_m=gate)
    with pytest.raises(ValueError, match="reference has shape"):
        band.observer(reference=half[:-1], gate_m=gate)


def test_bad_inputs_are_rejected(sphere):
    """A noise model without a weight floor, a depth image with NaN and a bad stride raise
    ValueError naming the problem (nothing is accumulated)."""
    band, frames = sphere
    with pytest.raises(ValueError, match="floor"):
        band.observer(depth_a_m=0.0, sigma_pose_m=0.0, sigma_model_m=0.0)
    obs = band.observer()
    frame = frames[0]
    bad = frame.depth_m.copy()
    bad[3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        obs.integrate(bad, frame.K, frame.T_W_C)
    with pytest.raises(ValueError, match="stride"):
        obs.integrate(frame.depth_m, frame.K, frame.T_W_C, stride=0)
    S, h, stats = obs.finalize()
    assert stats["frames"] == 0 and not S.any() and not h.any()


def test_superpixels_keep_every_pixel_and_the_geometry():
    """observation.aggregate: where a voxel spans several pixels (here 160x120 frames, fx 200,
    3 cm voxels: 5-7 pixels a voxel) blocks of pixels on one surface are observed as one
    pixel at their mean depth with the information of all of them. Every valid pixel still
    counts once, the data term's total information is kept, and it still holds the box
    exactly: S x_true = h on the faces, to a small fraction of a voxel (noiseless depth);
    the pass handles about 10x fewer samples."""
    cfg = SyntheticConfig(mesh="box", radius_m=R_OBJ, width=160, height=120, fx=200.0,
                          fy=200.0, cx=79.5, cy=59.5, noise="none", quantization_m=0.0,
                          n_views=3, trajectory="ring", cam_radius_m=1.2, cam_height_m=0.7)
    frames = list(SyntheticDataset(cfg))
    band = Band(shell(box_sdf, 2.5))
    x_true = box_sdf((band.ijk + 0.5) * VOXEL)
    q = np.abs((band.ijk + 0.5) * VOXEL) - R_OBJ
    faces = np.sort(q, axis=1)[:, 1] < -2 * VOXEL  # two voxels or more from every edge
    out = {}
    for agg in (0.0, 1.0):
        obs = band.observer(aggregate=agg, count_once="voxel", front_m=2 * TRUNC)
        for f in frames:
            obs.integrate(f.depth_m, f.K, f.T_W_C)
        S, h, stats = obs.finalize()
        res = stencil_matrix(S, band.nbr) @ x_true - h
        seen = faces & (S[:, 13] > 0.05 * S[:, 13].max())
        out[agg] = dict(stats=stats, total=float(S.astype(np.float64).sum()),
                        res=np.abs(res[seen]) / np.abs(S[seen]).sum(axis=1) / VOXEL)
    off, on = out[0.0], out[1.0]
    assert on["stats"]["pixels_valid"] == off["stats"]["pixels_valid"] > 30000
    assert on["stats"]["samples_accepted"] < 0.2 * off["stats"]["samples_accepted"]
    assert abs(on["total"] / off["total"] - 1) < 0.01  # sum of S = sum of the weights
    assert np.median(on["res"]) < 0.005 and np.percentile(on["res"], 95) < 0.02
    assert np.percentile(off["res"], 95) < 1e-4  # the reference: exact rows


def test_superpixels_are_planar_blocks():
    """A block of pixels is observed as one super-pixel only where it is one plane within the
    sensor noise (kernels.funcs.block_is_planar): on a tilted plane with the axial noise the
    4 x 4 blocks form, and the blocks straddling a 3 cm step (well within the range test's
    slope limit) are observed in smaller blocks, so no block's mean depth lies between the two
    surfaces (also not a 2 x 2 block's, which is tested with its ring of pixels); every valid
    pixel is still observed once."""
    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    v, u = np.mgrid[0:120, 0:160]
    rng = np.random.default_rng(0)
    noise = 0.0012 + 0.0019 * (1.0 - 0.4) ** 2  # the default axial model at 1 m
    plane = 1.0 + 0.002 * (u - 80) + 0.001 * (v - 60)
    # inside the 4 x 4 blocks of columns 80-83 and between the two columns of the 2 x 2
    # blocks of columns 80-81, which four pixels alone would take for a plane
    step = np.where(u >= 81, 0.03, 0.0)
    obs = Band(shell(box_sdf, 2.5)).observer(aggregate=1.0, count_once="voxel",
                                             front_m=2 * TRUNC)
    for depth, straddle in ((plane, False), (plane + step, True)):
        depth = (depth + rng.normal(0, noise, depth.shape)).astype(np.float32)
        d, prm = obs._frame_params(depth, K, np.eye(4), None)
        levels = {k: (img, mask) for img, mask, _, k in obs._levels(d, prm, 1)}
        assert max(levels) == 4  # f voxel / depth = 6 pixels: blocks of up to 4 x 4
        img4, mask4 = levels[4]
        seen = sum(int((m == 1).sum()) * k * k for k, (_, m) in levels.items())
        assert seen == depth.size  # every valid pixel once
        assert (mask4 == 1).mean() > 0.95 if not straddle else (mask4 == 1).mean() > 0.9
        col = mask4[:, 20]  # the blocks of columns 80-83
        assert (col == 1).all() != straddle
        if straddle:  # what a block observes is on one of the two surfaces
            for k, (img, m) in levels.items():
                if k > 1:
                    vv, uu = np.nonzero(m == 1)
                    ref = (plane + step)[vv * k + k // 2, uu * k + k // 2]
                    assert np.abs(img[vv, uu] - ref).max(initial=0) < 0.01


@pytest.mark.parametrize("count_once", ["pixel", "voxel"])
def test_misfit_sums_match_a_reference_built_from_the_rows(sphere, count_once):
    """The misfit pass (which looks up only the samples near the surface, and the others only
    until a pixel's share is settled) sums exactly what the rows of the data term give: per
    corner, a_c s min(r^2, 100 sigma^2), a_c s max(sigma^2 - p, 0.1 sigma^2), a_c s, and a_c s
    times rc, y, y^2 and rc y over the accepted samples with |y| < MISFIT_NEAR voxels; r = y -
    a . mu, rc = r clipped to +-10 sigma, p = sum a_c^2 var_c, sigma^2 the sample's pixel
    noise, s its share of the pixel."""
    band, frames = sphere
    rng = np.random.default_rng(3)
    centres = (band.ijk + 0.5) * VOXEL
    mu = (sphere_sdf(centres) + rng.normal(0, 0.004, len(centres))).astype(np.float32)
    var = np.full(len(centres), 1e-6, np.float32)
    ref = sphere_sdf(centres).astype(np.float32)
    obs = band.observer(count_once=count_once, front_m=2 * TRUNC, gate_m=0.5 * TRUNC,
                        reference=ref)
    expected = np.zeros((len(centres), 7))
    for f in frames:
        obs.misfit(f.depth_m, f.K, f.T_W_C, mu, var)
        rows = obs.frame_rows(f.depth_m, f.K, f.T_W_C)
        _, first, n_acc = np.unique(rows["pixel"], return_inverse=True, return_counts=True)
        n_share = n_acc[first].astype(np.float64)
        if count_once == "voxel":
            n_share = np.minimum(n_share, obs.share)
        sigma2 = 1.0 / (rows["w"] * n_share)
        s = 1.0 / n_share
        near = np.abs(rows["y"]) < MISFIT_NEAR * VOXEL
        a, idx = rows["a"][near], rows["idx"][near]
        r = rows["y"][near] - (a * mu[idx]).sum(axis=1)
        p = (a ** 2 * var[idx]).sum(axis=1)
        rc = np.clip(r, -10 * np.sqrt(sigma2[near]), 10 * np.sqrt(sigma2[near]))
        y = rows["y"][near]
        terms = (np.minimum(r ** 2, 100 * sigma2[near]),
                 np.maximum(sigma2[near] - p, 0.1 * sigma2[near]), np.ones(near.sum()),
                 rc, y, y * y, rc * y)
        for col, t in enumerate(terms):
            np.add.at(expected[:, col], idx.ravel(), (a * (s[near] * t)[:, None]).ravel())
    assert expected[:, 2].sum() > 10  # many near samples were summed
    assert np.abs(expected[:, 6]).sum() > 0  # the residuals' line has something to fit
    # each add is rounded to 2^-24 of a voxel (^2) unit: a few units per sum
    unit = np.array([VOXEL ** 2, VOXEL ** 2, 1.0, VOXEL, VOXEL, VOXEL ** 2, VOXEL ** 2]) \
        * 2.0 ** -24
    np.testing.assert_allclose(obs.misfit_sums(), expected, rtol=1e-6, atol=32 * unit.max())
    assert np.all(np.abs(obs.misfit_sums() - expected) <= 1e-6 * np.abs(expected) + 32 * unit)


def test_release_drops_the_data_term_only(sphere):
    """After release() the misfit pass still runs (and sums the same); integrate and finalize
    refuse until reset(), which starts a data term from zero."""
    band, frames = sphere
    mu = sphere_sdf((band.ijk + 0.5) * VOXEL).astype(np.float32)
    var = np.full(len(mu), 1e-6, np.float32)
    kept, released = band.observer(), band.observer()
    for obs in (kept, released):
        for f in frames:
            obs.integrate(f.depth_m, f.K, f.T_W_C)
    S, h, _ = released.finalize()
    released.release()
    for obs in (kept, released):
        for f in frames:
            obs.misfit(f.depth_m, f.K, f.T_W_C, mu, var)
    np.testing.assert_array_equal(released.misfit_sums(), kept.misfit_sums())
    f = frames[0]
    with pytest.raises(RuntimeError, match="release"):
        released.integrate(f.depth_m, f.K, f.T_W_C)
    with pytest.raises(RuntimeError, match="release"):
        released.finalize()
    released.reset()
    for f in frames:
        released.integrate(f.depth_m, f.K, f.T_W_C)
    S2, h2, _ = released.finalize()
    np.testing.assert_array_equal(S2, S)
    np.testing.assert_array_equal(h2, h)
