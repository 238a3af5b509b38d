from pathlib import Path

import pytest
import yaml

from gtgen.config import GtgenConfig, build_config, configs_dir, default_yaml, load_config
from gtgen.errors import ConfigError, InputNotFoundError


def test_default_yaml_lists_every_key_and_matches_the_models():
    text = (configs_dir() / "default.yaml").read_text()
    assert text.strip() == default_yaml().strip(), "configs/default.yaml is stale: regenerate from gtgen.config.default_yaml()"
    assert build_config(yaml.safe_load(text)) == GtgenConfig()


def test_presets_yaml_mirror_the_code_and_load():
    from gtgen.train.presets import PRESETS, preset_overrides, preset_yaml

    files = {p.stem: p for p in (configs_dir() / "presets").glob("*.yaml")}
    assert set(files) == set(PRESETS)
    for name, p in files.items():
        assert p.read_text() == preset_yaml(name), f"configs/presets/{name}.yaml is stale: run scripts/update_schema_doc.py"
        layer = preset_overrides(name)
        assert load_config(None, layer).train.preset == name
        assert load_config(p).train.micro_size == PRESETS[name].train["micro_size"]
    with pytest.raises(ConfigError, match="unknown; expected one of"):
        preset_overrides("huge")


def test_xracer_yaml_is_the_default_topic_mapping():
    assert load_config(configs_dir() / "xracer.yaml") == GtgenConfig()


def test_partial_override_keeps_other_defaults(tmp_path: Path):
    p = tmp_path / "c.yaml"
    p.write_text("fuse:\n  window_s: 30\n")
    cfg = load_config(p)
    assert cfg.fuse.window_s == 30
    assert cfg.fuse.min_conf == 0.1
    assert cfg.grids.micro.size == 500


@pytest.mark.parametrize(
    "text, needle",
    [
        ("fuse:\n  window_s: -1\n", "fuse.window_s"),
        ("fuse:\n  windw_s: 3\n", "config key 'fuse.windw_s' is not a gtgen setting; did you mean 'fuse.window_s'?"),
        ("fuze:\n  window_s: 3\n", "config key 'fuze' is not a gtgen setting; did you mean 'fuse'?"),
        ("dem:\n  qqq: 3\n", "config key 'dem.qqq' is not a gtgen setting; dem takes: enabled, dir, min_fitness"),
        ("fuse:\n  window_s: .inf\n", "config key 'fuse.window_s' = inf: Input should be a finite number"),
        ("grids:\n  micro:\n    resolution_m: 0\n", "grids.micro.resolution_m"),
        ("synth:\n  speed_min_mps: 9\n  speed_max_mps: 5\n", "speed_max_mps"),
        ("- a\n- b\n", "must hold a mapping"),
        ("fuse: [unclosed\n", "not valid YAML"),
    ],
)
def test_bad_config_is_one_clear_line(tmp_path: Path, text: str, needle: str):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert needle in msg and "\n" not in msg


def test_missing_config_file():
    with pytest.raises(InputNotFoundError, match="does not exist"):
        load_config(Path("/nonexistent/x.yaml"))


@pytest.mark.parametrize("over, needle", [
    ({"topics": {"map_short": "/xracer/map/micro"}}, "topics.map_micro and topics.map_short"),
    ({"topics": {"cameras": {"front": {"image": "/cam_front/image/compressed", "info": "/cam_front/camera_info"},
                             "left": {"image": "/cam_front/image/compressed", "info": "/cam_left/camera_info"}}}},
     "topics.cameras.front.image and topics.cameras.left.image"),
    ({"topics": {"gnss": "/tf"}}, "topics.gnss and topics.tf"),
    ({"topics": {"layers": {"risk": "elevation"}}}, "topics.layers names"),
])
def test_one_topic_in_two_roles_is_a_one_line_error(over, needle):
    with pytest.raises(ConfigError) as exc:
        build_config(over)
    assert needle in str(exc.value) and "\n" not in str(exc.value)


def test_a_cover_cell_that_would_split_a_cell_into_too_many_sub_cells_is_refused():
    """mapping.cover_cell_m splits coarse cells into sub-cells whose tops every cell of the
    rolling map keeps: 0.01 m would make 80 x 80 of them a 0.8 m cell (1.6 GB for the short
    map); a one-line error names the value, the grid and the smallest allowed."""
    from gtgen.config import build_config

    with pytest.raises(ConfigError) as exc:
        build_config({"mapping": {"cover_cell_m": 0.01}})
    msg = str(exc.value)
    assert "mapping.cover_cell_m = 0.01" in msg and "short grid's 0.8 m cells into 80 x 80" in msg and "\n" not in msg
    assert build_config({"mapping": {"cover_cell_m": 0.1}}).mapping.sub_cells(0.8) == 8
    assert build_config({"mapping": {"cover_cell_m": None}}).mapping.sub_cells(0.8) == 1
