"""``./run.sh demo`` (splat_slam_ros.demo): the configuration is read before any work, so a
bad ``--config`` is one ``error:`` line and exit 2 with nothing generated."""
from __future__ import annotations

from splat_slam_ros import demo


def test_bad_config_fails_before_generating(tmp_path, capsys):
    out = tmp_path / "out"
    assert demo.main(["--out", str(out), "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "error: config file not found" in capsys.readouterr().err
    assert not out.exists()
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapping:\n  no_such_key: 7\n")
    assert demo.main(["--out", str(out), "--config", str(bad)]) == 2
    assert not out.exists()
