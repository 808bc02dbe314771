"""Short clips with the default settings: a run either ends with a trajectory and a map, or
exits non-zero with the reason (never exit 0 with an identity trajectory and no map), for
splat-slam-run and splat-slam-launch. Also: metrics.json holds depth L1 vs the dataset."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from test_graph_support import PY, isolated_env, need_ros

TRAJ = Path(__file__).resolve().parents[2] / "shared" / "data" / "trajectories" / \
    "freiburg1_xyz-groundtruth.txt"


def clip(tmp_path_factory, frames, size):
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_synth import generate_sequence
    if not TRAJ.is_file():
        pytest.skip(f"{TRAJ} not found (../shared/data)")
    d = tmp_path_factory.mktemp(f"clip{frames}")
    generate_sequence(str(TRAJ), frames, size, d / "seq", overwrite=True, progress=False,
                      realism="realistic", fps=30)
    write_bag(open_dataset(d / "seq"), d / "bag", progress=False)
    return d / "seq", d / "bag"


@pytest.fixture(scope="module")
def clip20(tmp_path_factory):
    return clip(tmp_path_factory, 20, (320, 240))


@pytest.fixture(scope="module")
def clip120(tmp_path_factory):
    return clip(tmp_path_factory, 120, (320, 240))


def check_outcome(rc: int, stderr: str, out: Path) -> str:
    """The contract: 0 with a moving trajectory and a map, or 3 with the reason."""
    from splat_slam_ros.io.trajectory_io import read_trajectory
    assert "Traceback" not in stderr, stderr[-3000:]
    if rc == 0:
        _, P = read_trajectory(out / "trajectory_full.txt")
        assert np.abs(P - np.eye(4)).max() > 1e-6, "exit 0 with an identity trajectory"
        assert (out / "map.ply").stat().st_size > 1000
        return "mapped"
    assert rc == 3, (rc, stderr[-3000:])
    assert "never initialised" in stderr and "--set tracking." in stderr
    assert "error" in json.loads((out / "metrics.json").read_text())
    return "not initialised"


def run_cli(seq: Path, out: Path) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "splat_slam_ros.cli.run", str(seq), "--out", str(out),
                           "--no-progress"], capture_output=True, text=True, timeout=1800)


def run_launch(bag: Path, out: Path) -> subprocess.CompletedProcess:
    need_ros()
    return subprocess.run([PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(bag), "--out",
                           str(out)], capture_output=True, text=True, timeout=1800,
                          env=isolated_env())


def test_20_frame_clip_default_run(clip20, tmp_path):
    r = run_cli(clip20[0], tmp_path / "o")
    check_outcome(r.returncode, r.stderr, tmp_path / "o")


def test_20_frame_clip_default_launch(clip20, tmp_path):
    r = run_launch(clip20[1], tmp_path / "o")
    check_outcome(r.returncode, r.stderr, tmp_path / "o")


@pytest.mark.slow
def test_120_frame_320x240_clip_default_run(clip120, tmp_path):
    r = run_cli(clip120[0], tmp_path / "o")
    check_outcome(r.returncode, r.stderr, tmp_path / "o")


@pytest.mark.slow
def test_120_frame_320x240_clip_default_launch(clip120, tmp_path):
    r = run_launch(clip120[1], tmp_path / "o")
    check_outcome(r.returncode, r.stderr, tmp_path / "o")


def test_in_process_metrics_hold_depth_l1_against_the_dataset(tmp_path):
    """A tiny sequence that initialises: metrics.json has the map's depth L1 vs its depth."""
    from splat_slam_ros.config import load_config
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_synth import generate_sequence
    from splat_slam_ros.pipeline import run
    generate_sequence("builtin", 36, (160, 120), tmp_path / "seq", overwrite=True,
                      progress=False, realism="clean", fps=10)
    cfg = load_config(overrides={
        "tracking.warmup": 4, "tracking.motion_filter_thresh": 2.0,
        "tracking.keyframe_thresh": 2.0, "tracking.ba_downsample": 4,
        "mapping.iters_first": 40, "mapping.iters_per_keyframe": 8, "mapping.mesh": False})
    r = run(open_dataset(tmp_path / "seq"), cfg, tmp_path / "out", progress=False)
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["depth_l1_views"] >= 3 and m["depth_l1_views"] == m["keyframes"]   # tracker kfs
    assert 0 < m["depth_l1_cm"] < 100 and m["depth_l1_sim3_scale"] > 0
    assert m["map"]["skipped_iterations"] >= 0 and "refine" in m["timings_s"]
