"""A live run's tracking replayed in process: ``splat-slam-run --skip-frames FILE`` skips the
frames a live tracker skipped on arrival (its ``frames_skipped.txt``) as it skipped them."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from splat_slam_ros.config import load_config
from splat_slam_ros.io.datasets import open_dataset
from splat_slam_ros.io.trajectory_io import (SKIPPED_FRAMES, read_stamps, read_trajectory,
                                             write_stamps)

CFG = """
tracking: {warmup: 4, motion_filter_thresh: 2.0, keyframe_thresh: 2.0, ba_downsample: 4,
           loop_closure: false, global_ba: false}
"""


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    from splat_slam_synth import generate_sequence
    root = tmp_path_factory.mktemp("skip_replay")
    d = root / "seq"
    generate_sequence("builtin", 40, (160, 120), d, overwrite=True, progress=False,
                      realism="clean", fps=10)
    cfg = root / "cfg.yaml"
    cfg.write_text(CFG)
    return d, cfg


def _main(capsys, *args):
    from splat_slam_ros.cli.run import main
    code = main([*map(str, args), "--no-progress"])
    return code, capsys.readouterr().err.strip().splitlines()


def test_a_live_runs_skips_replayed_in_process_track_as_the_tracker_did(seq, capsys, tmp_path):
    """Frames listed are skipped, the others tracked, exactly as a tracker fed the same way
    (skip with the frame: bridges included); the counts say so."""
    from splat_slam_ros.tracking.tracker import Tracker
    d, cfg_file = seq
    ds = open_dataset(d)
    frames = list(ds)
    skipped = [f for f in frames[6:-1] if f.index % 3 != 0]      # after the warm-up, not last
    listed = tmp_path / SKIPPED_FRAMES
    write_stamps(listed, [f.timestamp for f in skipped], "test")
    assert np.allclose(read_stamps(listed), [f.timestamp for f in skipped], atol=1e-6)
    code, err = _main(capsys, d, "--out", tmp_path / "out", "--config", cfg_file,
                      "--tracking-only", "--skip-frames", listed)
    assert code == 0, err
    ts, P = read_trajectory(tmp_path / "out" / "trajectory_full.txt")
    tr = Tracker(load_config(cfg_file), ds.intrinsics)
    names = {f.index for f in skipped}
    for f in frames:
        if f.index in names:
            tr.skip(f.index, f.timestamp, f)
        else:
            tr.track(f)
    tr.finalize()
    ts_ref, P_ref = tr.trajectory_full()
    assert len(ts) == len(frames) and np.allclose(ts, ts_ref, atol=1e-6)
    assert np.allclose(P, P_ref, atol=1e-5)
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["skips_replayed"] == len(skipped)
    assert m["frames_skipped"] == tr.n_skipped and tr.n_skipped <= len(skipped)
    assert m["frames_tracked"] + m["frames_skipped"] + m["frames_lost"] == len(frames)
    assert len(tr.skipped_at) == len(skipped)          # bridged ones stay listed


def test_skip_frames_mistakes_are_one_line_errors(seq, capsys, tmp_path):
    d, cfg_file = seq
    out = tmp_path / "out"
    cases = [(tmp_path / "missing.txt", None, "no such file"),
             (tmp_path / "words.txt", "# x\n1.0\nnot a stamp\n", "not a numeric"),
             (tmp_path / "cols.txt", "1.0 2.0\n3.0 4.0\n", "one timestamp per line")]
    for path, text, msg in cases:
        if text is not None:
            Path(path).write_text(text)
        code, err = _main(capsys, d, "--out", out, "--tracking-only", "--skip-frames", path)
        assert code == 2 and len(err) == 1 and msg in err[0], (path, err)
    code, err = _main(capsys, d, "--out", out, "--skip-frames", cases[1][0], "--gt-poses",
                      "--gt-depth")
    assert code == 2 and len(err) == 1 and "--skip-frames" in err[0], err
