"""The configuration's two tiers: a small core a user tunes, everything else under
``advanced:`` in YAML files (splat_slam_ros/config.py CORE_KEYS, docs/configuration.md)."""
import pytest
import yaml

from splat_slam_ros import config_reference as ref
from splat_slam_ros.config import (ADVANCED, CORE_KEYS, ConfigError, SlamConfig, config_dir,
                                   dump_config, is_core, load_config)


def test_core_is_small_and_names_real_keys():
    flat = SlamConfig().flat()
    assert len(set(CORE_KEYS)) == len(CORE_KEYS)
    assert [k for k in CORE_KEYS if k not in flat] == []
    assert len(CORE_KEYS) <= 40 and len(flat) - len(CORE_KEYS) >= 100
    assert is_core("tracking.keyframe_thresh") and not is_core("tracking.flow_patch_stride")


def test_advanced_section_sets_the_same_key_as_the_dotted_name(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("tracking: {keyframe_thresh: 3.0}\n"
                 f"{ADVANCED}: {{tracking: {{loop_nms: 7}}, mapping: {{prune_every: 40}}}}\n")
    cfg = load_config(f)
    want = load_config(overrides={"tracking.keyframe_thresh": 3.0, "tracking.loop_nms": 7,
                                  "mapping.prune_every": 40})
    assert cfg == want and cfg.tracking.loop_nms == 7 and cfg.mapping.prune_every == 40
    # an advanced key at its section is read too (the dotted names are one schema)
    f.write_text("tracking: {keyframe_thresh: 3.0, loop_nms: 7}\n"
                 f"{ADVANCED}: {{mapping: {{prune_every: 40}}}}\n")
    assert load_config(f) == want


@pytest.mark.parametrize("text,match", [
    (f"{ADVANCED}: {{tracking: {{keyframe_thresh: 3.0}}}}", "core key"),
    (f"{ADVANCED}: {{tracking: {{no_such_key: 1}}}}", "unknown config key 'tracking.no_such_key'"),
    (f"{ADVANCED}: {{nosection: {{a: 1}}}}", "unknown config section 'nosection'"),
    (f"{ADVANCED}: [1, 2]", "must be a mapping of sections"),
    (f"{ADVANCED}: {{tracking: 3}}", "must be a mapping of keys"),
    (f"{ADVANCED}: {{tracking: {{loop_nms: many}}}}", "expects int"),
])
def test_advanced_section_errors_name_the_key(tmp_path, text, match):
    f = tmp_path / "bad.yaml"
    f.write_text(text + "\n")
    with pytest.raises(ConfigError, match=match):
        load_config(f)


def test_dump_writes_core_at_sections_and_the_rest_under_advanced(tmp_path):
    cfg = load_config(overrides={"tracking.loop_nms": 7, "mapping.seed": 3})
    data = yaml.safe_load(dump_config(cfg, tmp_path / "c.yaml").read_text())
    core = {f"{s}.{k}" for s, v in data.items() if s != ADVANCED and isinstance(v, dict)
            for k in v} | {k for k, v in data.items() if not isinstance(v, dict)}
    adv = {f"{s}.{k}" for s, v in data[ADVANCED].items() for k in v}
    assert core == set(CORE_KEYS) and adv == set(SlamConfig().flat()) - set(CORE_KEYS)
    assert data[ADVANCED]["tracking"]["loop_nms"] == 7 and data["mapping"]["seed"] == 3
    assert load_config(tmp_path / "c.yaml") == cfg


def test_shipped_presets_keep_advanced_keys_under_advanced():
    for p in sorted(config_dir().glob("*.yaml")):
        data = yaml.safe_load(p.read_text())
        misplaced = [f"{s}.{k}" for s, v in data.items() if s != ADVANCED and isinstance(v, dict)
                     for k in v if not is_core(f"{s}.{k}")]
        assert misplaced == [], f"{p.name}: move under {ADVANCED}: {misplaced}"
        load_config(p)


def test_reference_lists_the_core_first_and_each_advanced_key_in_its_section():
    text = ref.render()
    core = text.split("## Core keys", 1)[1].split("\n## ", 1)[0]
    assert all(f"| `{k}` |" in core for k in CORE_KEYS)
    assert "| `tracking.flow_patch_stride` |" not in core
    tracking = text.split("## tracking (advanced)", 1)[1].split("\n## ", 1)[0]
    assert "| `tracking.flow_patch_stride` |" in tracking
    assert "| `tracking.keyframe_thresh` |" not in tracking
