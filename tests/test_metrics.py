"""Geometry metrics (bftaichi.evaluation.metrics): Chamfer, accuracy, completeness, F-score, mesh loading."""

import math

import numpy as np
import pytest
import trimesh

from bftaichi.errors import BftaichiError, DataError
from bftaichi.io import write_mesh_ply
from bftaichi.evaluation.metrics import (SampledSurface, format_table, geometry_metrics,
                                        load_mesh, spearman, surface_distances,
                                        surface_distances_many, surface_sdf, uncertainty_metrics)
from bftaichi.evaluation.seen import seen_points

THRESHOLDS = (5, 10, 20, 50)


def unit_square(z=0.0, n=1):
    """The square [0,1]^2 at height z, triangulated as an n x n grid (normal +z)."""
    g = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(v, f, process=False)


def test_identical_meshes_give_zero_distance_and_full_fscore():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    m = geometry_metrics(mesh, mesh.copy(), n_samples=20000)
    assert m["chamfer_l2"] == 0.0
    assert m["accuracy_m"] == 0.0 and m["completeness_m"] == 0.0
    for t in THRESHOLDS:
        assert m[f"precision@{t}mm"] == 1.0
        assert m[f"recall@{t}mm"] == 1.0
        assert m[f"fscore@{t}mm"] == 1.0
    assert m["n_pred_faces"] == len(mesh.faces)


def test_offset_plane_distances_match_offset():
    """GT z=0 (2 triangles) vs prediction z=d (a 7x7 grid, so samples do not pair up exactly).

    Each sample's nearest neighbour on the other plane is at sqrt(d^2 + r^2), r the in-plane
    distance to the nearest sample. For N uniform samples on area A, E[r^2] = A / (pi N) (a
    Poisson process; up to twice that on the square's border), so with s = sqrt(A / N):
    d <= Acc, Comp <= sqrt(d^2 + s^2) and 2 d^2 <= CD <= 2 (d^2 + s^2). All P and G distances are
    >= d, so precision/recall at t <= d are exactly 0; at t = 20 mm they are 1 unless some sample
    has r > sqrt(t^2 - d^2) = 17 mm, i.e. a 17 mm disc (a quarter disc at a corner) without
    samples: probability ~ N exp(-pi r^2 N / 4) < 1e-50.
    """
    d = 0.010
    n = 200_000
    s = math.sqrt(1.0 / n)
    gt = unit_square(0.0, n=1)
    pred = unit_square(d, n=7)
    m = geometry_metrics(pred, gt, thresholds_mm=THRESHOLDS, n_samples=n, seed=3)
    for key in ("accuracy_m", "completeness_m"):
        assert d - 1e-12 <= m[key] <= math.sqrt(d * d + s * s)
        assert m[key] > d                     # the samples do not pair up: r > 0 on average
    assert 2 * d * d - 1e-15 <= m["chamfer_l2"] <= 2 * (d * d + s * s)
    for t in (5, 10):
        assert m[f"precision@{t}mm"] == 0.0 and m[f"recall@{t}mm"] == 0.0
        assert m[f"fscore@{t}mm"] == 0.0
    for t in (20, 50):
        assert m[f"precision@{t}mm"] == 1.0 and m[f"recall@{t}mm"] == 1.0
        assert m[f"fscore@{t}mm"] == 1.0


def test_half_coverage_halves_recall_not_precision():
    """A prediction covering half the GT square: precision 1, recall ~1/2, F = 2PR/(P+R)."""
    gt = unit_square(0.0, n=4)
    half = unit_square(0.0, n=4)
    half.vertices[:, 0] *= 0.5
    m = geometry_metrics(half, gt, thresholds_mm=(10,), n_samples=50000)
    p, r = m["precision@10mm"], m["recall@10mm"]
    assert p == 1.0
    assert 0.49 < r < 0.53                    # the 10 mm strip beyond x = 0.5 counts too
    assert m["fscore@10mm"] == pytest.approx(2 * p * r / (p + r))
    # completeness: mean distance of the uncovered half, (0.5 * 0.25 m) plus the covered ~0
    assert m["completeness_m"] == pytest.approx(0.125, rel=0.03)
    assert m["accuracy_m"] < 0.005


def test_empty_prediction_gives_inf_and_zero():
    gt = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    m = geometry_metrics(trimesh.Trimesh(), gt, n_samples=1000)
    assert math.isinf(m["chamfer_l2"]) and math.isinf(m["accuracy_m"])
    assert math.isinf(m["completeness_m"])
    assert m["n_pred_faces"] == 0
    for t in THRESHOLDS:
        assert m[f"precision@{t}mm"] == 0.0 and m[f"recall@{t}mm"] == 0.0
        assert m[f"fscore@{t}mm"] == 0.0


def test_empty_gt_and_bad_arguments_raise():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ValueError, match="gt"):
        geometry_metrics(mesh, trimesh.Trimesh())
    with pytest.raises(BftaichiError, match="thresholds_mm"):
        geometry_metrics(mesh, mesh, thresholds_mm=(0, 5))
    with pytest.raises(BftaichiError, match="n_samples"):
        geometry_metrics(mesh, mesh, n_samples=0)
    with pytest.raises(BftaichiError, match="pred"):
        geometry_metrics(np.zeros((3, 3)), mesh)


def test_same_seed_same_numbers_other_seed_other_samples():
    gt = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    pred = trimesh.creation.box(extents=(0.18, 0.18, 0.18))
    a = geometry_metrics(pred, gt, n_samples=20000, seed=7)
    b = geometry_metrics(pred, gt, n_samples=20000, seed=7)
    c = geometry_metrics(pred, gt, n_samples=20000, seed=8)
    assert a == b
    assert a["chamfer_l2"] != c["chamfer_l2"]
    assert a["chamfer_l2"] == pytest.approx(c["chamfer_l2"], rel=0.05)


def test_keys_and_json_ready_types():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    m = geometry_metrics(mesh, mesh, thresholds_mm=(2.5, 10), n_samples=500)
    assert list(m) == ["chamfer_l2", "accuracy_m", "completeness_m",
                       "precision@2.5mm", "recall@2.5mm", "fscore@2.5mm",
                       "precision@10mm", "recall@10mm", "fscore@10mm", "n_pred_faces"]
    assert all(type(v) is float for k, v in m.items() if k != "n_pred_faces")
    assert type(m["n_pred_faces"]) is int


# ---------------------------------------------------------------- load_mesh

def test_load_mesh_reads_bftaichi_ply_and_scenes(tmp_path):
    box = trimesh.creation.box(extents=(1, 2, 3))
    path = tmp_path / "mesh.ply"
    write_mesh_ply(path, box.vertices, box.faces,
                   vertex_attrs={"sigma": np.full(len(box.vertices), 0.01)})
    loaded = load_mesh(path)
    assert isinstance(loaded, trimesh.Trimesh)
    np.testing.assert_allclose(loaded.vertices, box.vertices, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, box.faces)
    # a scene of two meshes is concatenated
    scene = trimesh.Scene([box, box.copy().apply_translation((5, 0, 0))])
    scene.export(tmp_path / "scene.glb")
    both = load_mesh(tmp_path / "scene.glb")
    assert len(both.faces) == 2 * len(box.faces)
    assert both.area == pytest.approx(2 * box.area)


def test_load_mesh_errors_name_the_path(tmp_path):
    missing = tmp_path / "missing.ply"
    with pytest.raises(DataError, match="missing.ply"):
        load_mesh(missing)
    with pytest.raises(DataError, match="not a file"):
        load_mesh(tmp_path)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"this is not a ply file")
    with pytest.raises(DataError, match="garbage.ply"):
        load_mesh(garbage)
    unknown = tmp_path / "mesh.xyzabc"
    unknown.write_text("1 2 3\n")
    with pytest.raises(DataError, match="mesh.xyzabc"):
        load_mesh(unknown)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((20, 3))).export(cloud)
    with pytest.raises(DataError, match="cloud.ply.*no triangles"):
        load_mesh(cloud)


# ---------------------------------------------------------------- format_table

def test_format_table_aligned_with_units():
    m1 = {"chamfer_l2": 1.234e-5, "accuracy_m": 0.0031, "completeness_m": 0.01,
          "precision@5mm": 0.91234, "fscore@5mm": 0.5, "n_pred_faces": 1234}
    m2 = dict(m1, accuracy_m=math.inf, n_pred_faces=0)
    del m2["fscore@5mm"]
    table = format_table({"tsdf_mesh.ply": m1, "mesh.ply": m2})
    lines = table.splitlines()
    assert "tsdf_mesh.ply" in lines[0] and "mesh.ply" in lines[0]
    assert len(lines) == 2 + len(m1)
    assert len({len(line) for line in lines}) == 1          # every line padded to one width
    rows = {line.split("  ")[0].strip(): line.split()[-2:] for line in lines[2:]}
    assert rows["chamfer_l2 [m^2]"] == ["1.234e-05", "1.234e-05"]
    assert rows["accuracy [mm]"] == ["3.10", "inf"]
    assert rows["completeness [mm]"] == ["10.00", "10.00"]
    assert rows["precision@5mm"] == ["0.912", "0.912"]
    assert rows["fscore@5mm"] == ["0.500", "-"]
    assert rows["n_pred_faces"] == ["1234", "0"]
    # keys select and order the lines
    only = format_table({"a": m1}, keys=["n_pred_faces", "accuracy_m"]).splitlines()
    assert [line.split()[0] for line in only[2:]] == ["n_pred_faces", "accuracy"]


def test_surface_sdf_matches_the_analytic_sphere_and_its_sign():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.3)
    pts = np.random.default_rng(0).normal(size=(2000, 3))
    pts *= (0.3 + np.random.default_rng(1).uniform(-0.02, 0.02, (2000, 1))) / np.linalg.norm(
        pts, axis=1, keepdims=True)
    phi, valid = surface_sdf(sphere, pts, spacing_m=0.002)
    assert valid.all()  # closed mesh: no boundary, every sign defined
    # the icosphere's flat facets sit up to ~0.15 mm inside the analytic sphere
    np.testing.assert_allclose(phi, np.linalg.norm(pts, axis=1) - 0.3, atol=3e-4)


def test_surface_sdf_leaves_points_beyond_an_open_edge_undecided():
    plane = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    pts = np.array([[0.5, 0.5, 0.01], [0.5, 0.5, -0.02], [1.2, 0.5, 0.01], [np.nan, 0, 0]])
    phi, valid = surface_sdf(plane, pts, spacing_m=0.01)
    np.testing.assert_allclose(phi[:2], [0.01, -0.02], atol=1e-9)  # above: +, below: -
    assert valid.tolist() == [True, True, False, False]


def test_uncertainty_metrics_of_honest_gaussian_sigma():
    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.001, 0.005, 200_000)
    truth = rng.normal(size=sigma.size)
    u = uncertainty_metrics(truth + sigma * rng.normal(size=sigma.size), sigma, truth)
    assert abs(u["coverage@1sigma"] - 0.683) < 0.01 and abs(u["coverage@2sigma"] - 0.954) < 0.005
    assert abs(u["median_z"] - 0.674) < 0.01 and u["spearman"] > 0.3
    # a sigma twice too large is reported as conservative, and a constant one ranks nothing
    big = uncertainty_metrics(truth + sigma * rng.normal(size=sigma.size), 2 * sigma, truth)
    assert big["coverage@1sigma"] > 0.9 and big["median_z"] < 0.4
    flat = uncertainty_metrics(truth + sigma * rng.normal(size=sigma.size),
                               np.full(sigma.size, 0.003), truth)
    assert flat["ause"] > u["ause"]


def test_spearman_is_scipys_rank_correlation_with_ties():
    from scipy.stats import spearmanr

    rng = np.random.default_rng(3)
    a = rng.integers(0, 40, 5000).astype(float)  # many ties
    b = a + rng.normal(0, 15, a.size)
    for x, y in ((a, b), (b, a), (a, -b), (rng.normal(size=7), rng.normal(size=7))):
        assert spearman(x, y) == pytest.approx(spearmanr(x, y).statistic, rel=1e-12, abs=1e-14)
    assert spearman(np.ones(10), b[:10]) == 0.0  # a constant ranks nothing (scipy: NaN)


def test_distances_of_several_meshes_equal_separate_calls():
    gt = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    preds = [trimesh.creation.icosphere(subdivisions=2, radius=0.102), unit_square(n=2),
             trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))]
    many = surface_distances_many(preds, gt, 5000, seed=4)
    for pred, got in zip(preds, many):
        one = surface_distances(pred, gt, 5000, seed=4)
        assert (got is None) == (one is None)
        if one is not None:
            assert all(np.array_equal(u, v) for u, v in zip(got, one))
    assert many[2] is None  # no surface


def test_uncertainty_metrics_reject_bad_input():
    with pytest.raises(BftaichiError, match="one length"):
        uncertainty_metrics(np.zeros(3), np.ones(2), np.zeros(3))
    with pytest.raises(BftaichiError, match="finite"):
        uncertainty_metrics(np.array([0.0, np.nan]), np.ones(2), np.zeros(2))


def test_seen_points_are_those_no_surface_hid_from_a_frame():
    """A camera 2 m above the unit square, looking down (-z): points on the square are seen,
    the same points 5 cm below it are hidden by it, points outside the image are unseen, and a
    frame whose pixels are invalid sees nothing."""
    from types import SimpleNamespace

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # camera z along world -z
    T[:3, 3] = (0.5, 0.5, 2.0)
    D = np.full((101, 101), 2.0)  # the square fills the image at depth 2 m
    frame = SimpleNamespace(depth_m=D, K=K, T_W_C=T)
    rng = np.random.default_rng(0)
    on = np.c_[rng.uniform(0.3, 0.7, (200, 2)), np.zeros(200)]
    below = on - (0, 0, 0.05)
    outside = on + (5.0, 0, 0)
    seen = seen_points(np.r_[on, below, outside], [frame], lambda d: 0.001 + 0 * d)
    assert seen[:200].all() and not seen[200:].any()
    dark = SimpleNamespace(depth_m=np.zeros_like(D), K=K, T_W_C=T)
    assert not seen_points(on, [dark], lambda d: 0.001 + 0 * d).any()


def test_chamfer_split_adds_up_and_puts_a_missing_part_where_it_is_missing():
    """The parts of ``chamfer_split`` sum to geometry_metrics' chamfer_l2; a prediction that
    covers only half the square has its Chamfer distance in the uncovered half."""
    gt = unit_square(0.0, n=4)
    half = unit_square(0.0, n=4)
    half.vertices[:, 0] *= 0.5
    target = SampledSurface(gt, 20000, seed=0)
    mask = target.points()[:, 0] < 0.5
    inside, outside = target.chamfer_split(half, mask)
    total = geometry_metrics(half, gt, thresholds_mm=(10,), n_samples=20000)["chamfer_l2"]
    assert inside + outside == pytest.approx(total, rel=1e-12)
    assert inside < 1e-3 * outside  # sample spacing alone on the covered half
    with pytest.raises(BftaichiError):
        target.chamfer_split(half, mask[:-1])
