import re

import pytest

from splat_slam_ros.config import ConfigError, SlamConfig, config_dir, load_config


def test_defaults_follow_reference():
    c = SlamConfig()
    assert c.tracking.keyframe_thresh == 4.0 and c.tracking.global_ba_every == 20
    assert c.mapping.rgb_weight == 0.8 and c.mapping.isotropy_weight == 1.0   # paper: 10
    assert c.depth.mv_min_views == 2


def test_yaml_and_overrides(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("dataset: tum\ntracking:\n  keyframe_thresh: 3\nmapping:\n  window_size: 8\n")
    c = load_config(p, overrides={"mapping.iters_per_keyframe": 10})
    assert c.dataset == "tum" and c.tracking.keyframe_thresh == 3.0
    assert isinstance(c.tracking.keyframe_thresh, float)
    assert c.mapping.iters_per_keyframe == 10
    flat = c.flat()
    assert flat["tracking.keyframe_thresh"] == 3.0 and "ros.map_frame" in flat


@pytest.mark.parametrize("text,msg", [
    ("tracking:\n  no_such_key: 1\n", "unknown config key 'tracking.no_such_key'"),
    ("tracking:\n  warmup: 2.5\n", "'tracking.warmup' expects int"),
    ("tracking:\n  loop_closure: 3\n", "'tracking.loop_closure' expects bool"),
    ("nosection:\n  a: 1\n", "unknown config key 'nosection'"),
    ("- a\n- b\n", "must hold a mapping"),
    ("tracking: [unclosed\n", "not valid YAML"),
])
def test_bad_config_errors(file_error, text, msg):
    file_error("bad.yaml", text, load_config, ConfigError, re.escape(msg))


def test_missing_file_and_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="unknown config section"):
        load_config(overrides={"nothere.x": 1})


def test_shipped_configs_load():
    files = sorted(config_dir().glob("*.yaml"))
    for f in files:
        load_config(f)


def test_set_overrides_parse_and_reject_malformed():
    from splat_slam_ros.cli.common import parse_overrides
    assert parse_overrides(["tracking.warmup=6", "ros.map_frame=world"]) == {
        "tracking.warmup": 6, "ros.map_frame": "world"}
    with pytest.raises(ConfigError, match="--set expects KEY=VALUE"):
        parse_overrides(["tracking.warmup"])
