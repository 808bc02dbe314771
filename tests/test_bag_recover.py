"""Bags whose recorder was killed (MCAP without summary/index/footer): every complete message
up to the damage is read with a warning, --info reports it, --recover repairs it, and
splat-slam-run processes the recovered frames."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from splat_slam_ros.cli import convert
from splat_slam_ros.io import mcap_recover
from splat_slam_ros.io.datasets import open_dataset

from test_graph_support import TINY_FAST_RUN_CFG, write_tiny_bag


def _truncate(bag: Path, frac: float = 0.5) -> Path:
    f = next(bag.glob("*.mcap"))
    data = f.read_bytes()
    f.write_bytes(data[: int(len(data) * frac)])
    return f


@pytest.fixture()
def tiny_bag(tmp_path):
    return write_tiny_bag(tmp_path / "bag", n=40)


def test_truncated_bag_yields_the_frames_before_the_damage(tiny_bag, capsys):
    f = _truncate(tiny_bag)
    h = mcap_recover.scan_mcap(f)
    assert h.damaged and h.topics["/camera/image_raw"][1] >= 18
    for backend in ("auto", "mcap"):
        ds = open_dataset(tiny_bag, backend=backend) if backend != "auto" else open_dataset(tiny_bag)
        frames = list(ds.iter_frames())
        ds.close()
        assert 18 <= len(frames) < 40 and len(ds) == len(frames)
        assert all(fr.gt_pose is not None and fr.gt_depth is not None for fr in frames)
    err = capsys.readouterr().err
    assert f"read as a stream: {h.messages} complete messages recovered" in err
    # the bag player's reader recovers the same frames
    from splat_slam_nodes.tools.bag_player import BagReader, frames as player_frames
    r = BagReader(tiny_bag)
    assert sum(1 for _ in player_frames(r, list(r.types), "/camera/image_raw")) == len(frames)


def test_intact_bag_is_reported_intact(tiny_bag, capsys):
    assert convert.main([str(tiny_bag), "--info"]) == 0
    out = capsys.readouterr().out
    assert "intact (160 messages, indexed)" in out and "DAMAGED" not in out


def test_info_reports_damage_and_recover_repairs(tiny_bag, tmp_path, capsys):
    _truncate(tiny_bag)
    assert convert.main([str(tiny_bag), "--info"]) == 0
    out = capsys.readouterr().out
    assert "DAMAGED bag.mcap: damaged, no summary/index" in out and "--recover" in out
    fixed = tmp_path / "fixed"
    assert convert.main([str(tiny_bag), "--recover", "--out", str(fixed)]) == 0
    n_fixed = mcap_recover.scan_mcap(fixed / "bag.mcap")
    assert not n_fixed.damaged and n_fixed.messages == mcap_recover.scan_mcap(
        next(tiny_bag.glob("*.mcap"))).messages
    # the repaired folder is a valid rosbag2 bag for the rosbags reader too (metadata counts)
    ds = open_dataset(fixed, backend="rosbags")
    assert len(ds) == n_fixed.topics["/camera/image_raw"][1] == len(list(ds.iter_frames()))
    ds.close()
    capsys.readouterr()
    assert convert.main([str(tiny_bag), "--recover", "--out", str(fixed)]) == 2
    assert "exists" in capsys.readouterr().err
    assert convert.main([str(tmp_path / "nope"), "--recover", "--out", str(tmp_path / "x")]) == 2


def test_partial_compressed_chunk_is_recovered(tmp_path):
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_ros.io.datasets import open_dataset as od
    src = write_tiny_bag(tmp_path / "src", n=30)
    ds = od(src)
    write_bag(ds, tmp_path / "z", progress=False, compress=True)
    ds.close()
    f = _truncate(tmp_path / "z")
    h = mcap_recover.scan_mcap(f)
    assert h.damaged and h.topics["/camera/image_raw"][1] >= 10, h.describe()


RUN_CFG = TINY_FAST_RUN_CFG


def test_splat_slam_run_on_a_bag_truncated_at_half(tmp_path):
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_synth import generate_sequence
    seq = tmp_path / "seq"
    generate_sequence("builtin", 36, (160, 120), seq, overwrite=True, progress=False,
                      realism="clean", fps=5)          # 5 fps: enough motion in 18 frames
    with open_dataset(seq) as ds:
        write_bag(ds, tmp_path / "bag", progress=False)
    n_rec = mcap_recover.scan_mcap(_truncate(tmp_path / "bag")).topics["/camera/image_raw"][1]
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(RUN_CFG)
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.run", str(tmp_path / "bag"),
                        "--out", str(out), "--config", str(cfg), "--no-progress"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "complete messages recovered" in r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == n_rec >= 0.45 * 36 and m["keyframes"] >= 3, m


def test_splat_slam_launch_on_a_bag_truncated_at_half(tmp_path):
    from test_graph_support import PY, isolated_env, need_ros, start, stop
    need_ros()
    from splat_slam_ros.io.bagio import write_bag
    from splat_slam_synth import generate_sequence
    seq = tmp_path / "seq"
    generate_sequence("builtin", 36, (160, 120), seq, overwrite=True, progress=False,
                      realism="clean", fps=5)
    with open_dataset(seq) as ds:
        write_bag(ds, tmp_path / "bag", progress=False)
    n_rec = mcap_recover.scan_mcap(_truncate(tmp_path / "bag")).topics["/camera/image_raw"][1]
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(RUN_CFG)
    out, log = tmp_path / "out", tmp_path / "launch.log"
    p = start([PY, "-m", "splat_slam_nodes.tools.launch", "--bag", str(tmp_path / "bag"), "--out",
               str(out), "--config", str(cfg)], isolated_env(), log)
    try:
        rc = p.wait(timeout=900)
    finally:
        stop(p)
    text = log.read_text(errors="replace")
    assert rc == 0, text[-3000:]
    assert "complete messages recovered" in text
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == n_rec >= 0.45 * 36 and m["keyframes"] >= 3, m
