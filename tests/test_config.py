"""Run configuration: defaults, precedence, --set parsing, validation messages, paths, saving."""

import dataclasses
import re
import shutil
import tomllib
from pathlib import Path

import pytest

from bftaichi.config import Config, load_config, parse_override, save_config
from bftaichi.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
SHIPPED_SCENES = sorted(SCENES.glob("*.toml"))


def write_scene(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# --------------------------------------------------------------------------------------------
# defaults and precedence
# --------------------------------------------------------------------------------------------

def test_builtin_defaults_equal_shipped_default_scene():
    """`bftaichi run` without a scene file runs exactly scenes/default.toml."""
    from_file = load_config(SCENES / "default.toml")
    assert from_file == Config()
    assert load_config(None) == Config()


def test_default_scene_file_sets_only_known_values():
    """Each value written in scenes/default.toml is the built-in default; on drift the assertion
    names the key that differs."""
    data = tomllib.loads((SCENES / "default.toml").read_text())
    defaults = Config().to_dict()
    for section, table in data.items():
        for key, value in table.items():
            assert defaults[section][key] == value, f"{section}.{key}"


def test_precedence_set_over_scene_file_over_defaults(tmp_path):
    scene = write_scene(tmp_path / "s.toml", "[tsdf]\nvoxel_size_m = 0.02\ntrunc_m = 0.08\n")
    cfg = load_config(scene, ["tsdf.trunc_m=0.05"])
    assert cfg.tsdf.voxel_size_m == 0.02          # from the scene file
    assert cfg.tsdf.trunc_m == 0.05               # --set beats the scene file
    assert cfg.tsdf.alpha == Config().tsdf.alpha  # neither: the default
    assert cfg.synthetic == Config().synthetic    # untouched sections stay at their defaults


def test_later_set_wins(tmp_path):
    cfg = load_config(None, ["synthetic.n_views=5", "synthetic.n_views=7"])
    assert cfg.synthetic.n_views == 7


# --------------------------------------------------------------------------------------------
# --set value parsing
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, section, key, expected, typ", [
    ("tsdf.voxel_size_m=0.005", "tsdf", "voxel_size_m", 0.005, float),
    ("tsdf.max_weight=50", "tsdf", "max_weight", 50.0, float),        # int literal -> float field
    ("synthetic.n_views=7", "synthetic", "n_views", 7, int),
    ("synthetic.n_views=7.0", "synthetic", "n_views", 7, int),        # integral float -> int
    ("tsdf.integrate_rgb=true", "tsdf", "integrate_rgb", True, bool),
    ("synthetic.center_mesh = false", "synthetic", "center_mesh", False, bool),
    ("eval.thresholds_mm=[1, 2.5, 10]", "eval", "thresholds_mm", [1.0, 2.5, 10.0], list),
    ("synthetic.look_at=[0, 0, 0.1]", "synthetic", "look_at", [0.0, 0.0, 0.1], list),
    ("synthetic.mesh=sphere", "synthetic", "mesh", "sphere", str),    # bare word
    ('scene.name="my scene"', "scene", "name", "my scene", str),      # quoted string
    ("scene.name=my scene", "scene", "name", "my scene", str),        # bare words with a space
    ("scene.frames=0:10:2", "scene", "frames", "0:10:2", str),
    ("scene.frames=3", "scene", "frames", "3", str),                  # a number into a text field
    ("scene.name=2024", "scene", "name", "2024", str),
    ("scene.format=bfsdf", "scene", "format", "bfsdf", str),
])
def test_set_values_are_parsed_to_the_field_type(text, section, key, expected, typ):
    cfg = load_config(None, [text])
    value = getattr(getattr(cfg, section), key)
    assert value == expected
    assert type(value) is typ
    if typ is list:
        assert all(type(v) is float for v in value)


def test_parse_override_splits_at_the_first_equals_sign():
    assert parse_override('scene.name="a=b"') == ("scene", "name", "a=b")


@pytest.mark.parametrize("text", ["tsdf.voxel_size_m", "voxel_size_m=0.01", "a.b.c=1"])
def test_malformed_set_is_a_config_error(text):
    with pytest.raises(ConfigError, match="section.key"):
        load_config(None, [text])


# --------------------------------------------------------------------------------------------
# validation: unknown keys, wrong types, out-of-range values
# --------------------------------------------------------------------------------------------

def test_unknown_section_is_named_with_suggestion():
    with pytest.raises(ConfigError, match=r"'tsdff'.*did you mean 'tsdf'"):
        load_config(None, ["tsdff.voxel_size_m=0.02"])


def test_unknown_key_is_named_with_suggestion():
    with pytest.raises(ConfigError, match=r"'voxel_sise_m'.*did you mean 'voxel_size_m'"):
        load_config(None, ["tsdf.voxel_sise_m=0.02"])


def test_unknown_key_in_scene_file_names_key_and_file(tmp_path):
    scene = write_scene(tmp_path / "typo.toml", "[synthetic]\nn_veiws = 12\n")
    with pytest.raises(ConfigError) as e:
        load_config(scene)
    msg = str(e.value)
    assert "n_veiws" in msg and "n_views" in msg and str(scene) in msg


def test_top_level_value_outside_a_section_is_rejected(tmp_path):
    scene = write_scene(tmp_path / "flat.toml", "voxel_size_m = 0.01\n")
    with pytest.raises(ConfigError, match="voxel_size_m"):
        load_config(scene)


@pytest.mark.parametrize("text, key", [
    ("synthetic.n_views=2.5", "synthetic.n_views"),
    ("synthetic.n_views=true", "synthetic.n_views"),   # a bool is not an int
    ("tsdf.voxel_size_m=abc", "tsdf.voxel_size_m"),
    ("tsdf.integrate_rgb=1", "tsdf.integrate_rgb"),
    ("eval.thresholds_mm=5", "eval.thresholds_mm"),
    ('eval.thresholds_mm=["a"]', "eval.thresholds_mm"),
])
def test_wrong_type_names_the_key(text, key):
    with pytest.raises(ConfigError, match=r"wrong type") as e:
        load_config(None, [text])
    assert key in str(e.value)


def test_wrong_type_in_scene_file_names_key_and_file(tmp_path):
    scene = write_scene(tmp_path / "bad.toml", '[tsdf]\nvoxel_size_m = "fine"\n')
    with pytest.raises(ConfigError) as e:
        load_config(scene)
    assert "tsdf.voxel_size_m" in str(e.value) and str(scene) in str(e.value)


@pytest.mark.parametrize("sets, key", [
    (["tsdf.voxel_size_m=0"], "tsdf.voxel_size_m"),
    (["tsdf.voxel_size_m=-0.01"], "tsdf.voxel_size_m"),
    (["tsdf.voxel_size_m=5.0", "tsdf.trunc_m=15"], "tsdf.voxel_size_m"),   # absurd 5 m voxels
    (["tsdf.voxel_size_m=nan"], "tsdf.voxel_size_m"),
    (["tsdf.voxel_size_m=0.02", "tsdf.trunc_m=0.01"], "tsdf.trunc_m"),    # less than one voxel
    (["tsdf.alpha=0.5"], "tsdf.alpha"),
    (["tsdf.alpha=4"], "tsdf.alpha"),
    (["synthetic.n_views=0"], "synthetic.n_views"),
    (["synthetic.dropout=1.5"], "synthetic.dropout"),
    (["synthetic.dropout=-0.1"], "synthetic.dropout"),
    (["synthetic.width=0"], "synthetic.width"),
    (["scene.depth_min_m=2", "scene.depth_max_m=1"], "scene.depth_max_m"),
    (["scene.source=camera"], "scene.source"),
    (["scene.source=dataset"], "scene.data"),      # a dataset scene needs a folder
    (["scene.frames=a:b"], "scene.frames"),
    (["scene.frames=0:10:0"], "scene.frames"),
    (["eval.thresholds_mm=[]"], "eval.thresholds_mm"),
    (["eval.thresholds_mm=[5, -1]"], "eval.thresholds_mm"),
    (["mesh.min_weight=0"], "mesh.min_weight"),
    (["run.arch=tpu"], "run.arch"),
])
def test_out_of_range_value_names_the_key(sets, key):
    with pytest.raises(ConfigError) as e:
        load_config(None, sets)
    assert key in str(e.value)


def test_out_of_range_value_in_scene_file_is_rejected(tmp_path):
    scene = write_scene(tmp_path / "big.toml", "[tsdf]\nvoxel_size_m = 5.0\ntrunc_m = 15.0\n")
    with pytest.raises(ConfigError, match="tsdf.voxel_size_m"):
        load_config(scene)


# --------------------------------------------------------------------------------------------
# scene files
# --------------------------------------------------------------------------------------------

def test_toml_syntax_error_names_the_file(tmp_path):
    scene = write_scene(tmp_path / "broken.toml", "[tsdf\nvoxel_size_m = 0.01\n")
    with pytest.raises(ConfigError, match="not valid TOML") as e:
        load_config(scene)
    assert str(scene) in str(e.value)


def test_missing_scene_file_is_named(tmp_path):
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match="does not exist") as e:
        load_config(missing)
    assert str(missing) in str(e.value)


def test_scene_file_that_is_a_folder_is_rejected(tmp_path):
    with pytest.raises(ConfigError, match=re.escape(str(tmp_path))):
        load_config(tmp_path)


def test_relative_paths_resolve_against_the_scene_files_folder(tmp_path, monkeypatch):
    scene = write_scene(tmp_path / "scenes" / "rel.toml", (
        '[scene]\nsource = "dataset"\ndata = "../data/seq"\ngt_mesh = "meshes/gt.ply"\n'
        '[synthetic]\nmesh = "../meshes/obj.ply"\n'))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)   # the working directory must not matter
    cfg = load_config(scene)       # none of the files exists: config does not check existence
    assert Path(cfg.scene.data).is_absolute()
    assert Path(cfg.scene.data).resolve() == (tmp_path / "data" / "seq").resolve()
    assert Path(cfg.scene.gt_mesh).resolve() == (tmp_path / "scenes" / "meshes" / "gt.ply").resolve()
    assert Path(cfg.synthetic.mesh).resolve() == (tmp_path / "meshes" / "obj.ply").resolve()


def test_relative_set_paths_resolve_against_the_working_directory(tmp_path, monkeypatch):
    scene = write_scene(tmp_path / "scenes" / "s.toml", "[tsdf]\nvoxel_size_m = 0.02\n")
    monkeypatch.chdir(tmp_path)
    cfg = load_config(scene, ["scene.source=dataset", "scene.data=frames/seq"])
    assert Path(cfg.scene.data).resolve() == (tmp_path / "frames" / "seq").resolve()


def test_home_and_variables_are_expanded(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("BFT_DATA", str(tmp_path / "store"))
    cfg = load_config(None, ["scene.source=dataset", "scene.data=~/seq",
                             "synthetic.mesh=$BFT_DATA/bunny.obj"])
    assert Path(cfg.scene.data) == tmp_path / "home" / "seq"
    assert Path(cfg.synthetic.mesh) == tmp_path / "store" / "bunny.obj"


def test_primitive_mesh_names_are_not_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert load_config(None, ["synthetic.mesh=box"]).synthetic.mesh == "box"
    assert load_config(None, ["scene.gt_mesh=auto"]).scene.gt_mesh == "auto"


def test_save_config_round_trips(tmp_path):
    cfg = load_config(None, [
        "scene.name=roundtrip", "scene.source=dataset", f"scene.data={tmp_path / 'seq'}",
        "scene.frames=0:50:5", "synthetic.look_at=[0.1, -0.2, 0.3]", "synthetic.n_views=9",
        "tsdf.voxel_size_m=0.004", "tsdf.trunc_m=0.012", "tsdf.integrate_rgb=true",
        "eval.thresholds_mm=[1, 2]", "run.seed=3"])
    path = tmp_path / "out" / "config.toml"
    path.parent.mkdir()
    save_config(cfg, path)
    assert tomllib.loads(path.read_text())["tsdf"]["voxel_size_m"] == 0.004
    back = load_config(path)
    assert back == cfg
    assert dataclasses.asdict(back) == dataclasses.asdict(cfg)


# --------------------------------------------------------------------------------------------
# shipped scenes
# --------------------------------------------------------------------------------------------

def test_there_are_shipped_scenes():
    assert {p.stem for p in SHIPPED_SCENES} >= {"default", "seed_sphere", "bunny", "redkitchen"}


@pytest.mark.parametrize("scene", SHIPPED_SCENES, ids=lambda p: p.stem)
def test_shipped_scene_loads_and_validates(scene):
    cfg = load_config(scene)
    assert cfg.scene.name == scene.stem  # the default output folder out/<name> is the file's name
    s = cfg.synthetic
    if cfg.scene.source == "synthetic":
        # The principal point lies inside the image (a copy-paste of 320x240 intrinsics onto a
        # smaller image would make every ray miss the scene).
        assert 0 <= s.cx <= s.width - 1 and 0 <= s.cy <= s.height - 1
    else:
        assert Path(cfg.scene.data).is_absolute()


@pytest.mark.parametrize("name", ["bunny", "redkitchen"])
def test_scenes_on_shared_data_load_without_the_data(name, tmp_path):
    """Config never checks that data exists (the run does): a copy of the scene file in a place
    where ../../shared/data does not exist still loads, with the path resolved next to it."""
    copy = tmp_path / "a" / "b" / f"{name}.toml"
    copy.parent.mkdir(parents=True)
    shutil.copy(SCENES / f"{name}.toml", copy)
    cfg = load_config(copy)
    path = Path(cfg.scene.data if cfg.scene.source == "dataset" else cfg.synthetic.mesh)
    assert not path.exists()
    assert path.resolve().is_relative_to((tmp_path / "shared" / "data").resolve())


def test_principal_point_outside_image_is_rejected():
    # Shrinking the image but not the principal point would silently render empty frames.
    with pytest.raises(ConfigError, match="synthetic.cx"):
        load_config(None, ["synthetic.width=64", "synthetic.height=48"])


@pytest.mark.parametrize("override, key", [
    ("eval.seed=-1", "eval.seed"),  # used to fail in the metrics, after the whole run
    ("run.seed=-1", "run.seed"),
    ("solver.seed=1099511627776", "solver.seed"),
    ("synthetic.fx=1e-6", "synthetic.fx"),  # a 180-degree camera: the renderer never ended
    ("scene.depth_max_m=1e12", "scene.depth_max_m"),  # a traceback in the ray caster
    ("mesh.min_weight=1e12", "mesh.min_weight"),  # failed after the TSDF: nothing to mesh
    ('nbv.poses_file="/no/such/poses.txt"', "nbv.poses_file"),  # failed at the nbv stage
])
def test_values_that_used_to_fail_late_are_refused_before_any_work(override, key, tmp_path,
                                                                    capsys):
    from bftaichi.cli import main

    extra = ["nbv.candidates=file", "nbv.enabled=true"] if "poses_file" in override else []
    with pytest.raises(ConfigError, match=re.escape(key)):
        load_config(None, [override, *extra])
    out = tmp_path / "out"
    argv = ["run", "-q", "--out", str(out)]
    for s in (override, *extra):
        argv += ["--set", s]
    assert main(argv) == 2
    assert key in capsys.readouterr().err
    assert not out.exists()  # refused before the output folder was touched
