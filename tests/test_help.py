"""Every executable answers ``--help`` with its description and exits 0, without starting ROS
(a node that ignored ``--help`` used to start and wait for input)."""
import configparser
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO


def console_scripts():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    lines = cfg["options.entry_points"]["console_scripts"].strip().splitlines()
    return [ln.split("=")[0].strip() for ln in lines if ln.strip()]


def test_every_console_script_is_listed():
    names = console_scripts()
    assert {"splat-slam-tracker-node", "splat-slam-depth-node", "splat-slam-mapper-node",
            "splat-slam-loop-closure-node", "splat-slam-rerun-logger",
            "splat-slam-launch", "splat-slam-run"} <= set(names)


@pytest.mark.parametrize("name", console_scripts())
def test_help_exits_0_without_starting_ros(name):
    exe = Path(sys.executable).with_name(name)
    assert exe.is_file(), f"{exe} not installed (run ./run.sh setup)"
    r = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120,
                       stdin=subprocess.DEVNULL)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-2000:]
    assert len(r.stdout.strip().splitlines()) >= 3, out[-2000:]
    # a started node logs through rclpy ("[INFO] [<stamp>] [<node>]: ...") or waits for input
    assert "[INFO]" not in out and "listening on" not in out, out[-2000:]
