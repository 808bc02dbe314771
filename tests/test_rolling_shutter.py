"""Rolling-shutter rectification (tracking/rolling_shutter.py) against the generator's
rolling-shutter renders, and its settings in the tracker."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import splat_slam_synth as synth
from splat_slam_ros.tracking.rolling_shutter import (ReadoutMotion, angular_velocity, readout_motion,
                                                     rectify, row_times)
from splat_slam_ros.tracking.tracker import Tracker, TrackingError
from test_synth_scenes import _pan, _shift


def test_row_times_follow_the_stamp_row():
    assert row_times(5, 0.02, 1.0) == pytest.approx([-0.02, -0.015, -0.01, -0.005, 0.0])
    assert row_times(3, 0.02, 0.0) == pytest.approx([0.0, 0.01, 0.02])
    assert row_times(3, 0.02, 0.5) == pytest.approx([-0.01, 0.0, 0.01])


def test_rectification_undoes_the_skew_of_a_pan():
    """A 1.5 rad/s pan read out in 30 ms: the generator's rolling-shutter frame (bottom row at
    the stamp) rectified at the pan's angular velocity matches the global-shutter frame; at
    the opposite angular velocity it is skewed twice as much."""
    rs_ms, H = 30.0, 96
    gs = synth.plan_sequence(_pan(), 3, "128x96", seed=3, start=0.5, warn=False)
    rsp = replace(gs, realism=synth.resolve_realism(rolling_shutter_ms=rs_ms).validate(gs.fps))
    img_g, img_r = gs.render(2)[0], rsp.render(2)[0]
    t, P = _pan()
    w = angular_velocity(P[100][:3, :3].T @ P[101][:3, :3], t[101] - t[100])
    assert np.linalg.norm(w) == pytest.approx(1.5, rel=1e-6)
    K = gs.intrinsics
    intr = (K.fx, K.fy, K.cx, K.cy)
    still = np.zeros(3)
    fixed = rectify(img_r, intr, ReadoutMotion(w, still, 0.0), rs_ms * 1e-3, 1.0)
    wrong = rectify(img_r, intr, ReadoutMotion(-w, still, 0.0), rs_ms * 1e-3, 1.0)
    # a pure rotation: the same with the depth given (no velocity)
    assert np.array_equal(fixed, rectify(img_r, intr, ReadoutMotion(w, still, 3.0),
                                         rs_ms * 1e-3, 1.0))
    top = slice(0, 16)
    before = abs(_shift(img_g[top], img_r[top]))
    assert before > 0.7 * K.fx * 1.5 * rs_ms * 1e-3 * (1 - 7.5 / (H - 1))
    assert abs(_shift(img_g[top], fixed[top])) < 0.15 * before
    assert abs(_shift(img_g[top], wrong[top])) > 1.5 * before
    mid = slice(24, 72)
    assert np.abs(fixed[mid].astype(float) - img_g[mid]).mean() < \
        0.5 * np.abs(img_r[mid].astype(float) - img_g[mid]).mean()


def test_no_readout_or_no_rotation_leaves_the_image():
    img = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    intr = (30.0, 30.0, 15.5, 11.5)
    turn = ReadoutMotion(np.array([0.0, 1.0, 0.0]), np.zeros(3), 0.0)
    assert rectify(img, intr, turn, 0.0, 1.0) is img
    assert rectify(img, intr, None, 0.02, 1.0) is img
    assert rectify(img, intr, turn._replace(omega=np.zeros(3)), 0.02, 1.0) is img


def test_the_translation_moves_rows_as_a_plane_at_the_depth():
    """Moving sideways at 1 unit/s past a plane 2 units away during a 20 ms readout (bottom
    row at the stamp): the top row's camera was 0.02 behind, so a point shows fx 0.02 / 2 =
    0.5 px further along x in the top row than the stamp's camera sees it; the bottom row is
    the stamp's, with or without a faint rotation."""
    H, W, fx = 48, 64, 50.0
    img = np.tile((np.arange(W) * 4 % 256).astype(np.uint8), (H, 1))
    intr = (fx, fx, (W - 1) / 2, (H - 1) / 2)
    m = readout_motion(np.array([[1, 0, 0, 0.05], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
                       0.05, depth=2.0)
    assert m.velocity == pytest.approx([1.0, 0.0, 0.0]) and m.depth == 2.0
    for omega in (np.zeros(3), np.array([0.0, 0.0, 1e-9])):
        out = rectify(img.astype(np.float32), intr, m._replace(omega=omega), 0.02, 1.0)
        # pixel x of the rectified top row samples x + 0.5 of the input (4 grey levels a px)
        assert out[0, 10:50] == pytest.approx(img[0, 10:50] + 2.0, abs=1e-3)
        assert out[-1, 10:50] == pytest.approx(img[-1, 10:50], abs=1e-3)


def test_the_tracker_rectifies_with_its_motion_and_checks_the_settings():
    """Every tracked frame gets the motion model's motion; the warm-up keyframes, which came
    before any, get the initialisation's (its keyframes rectified and their flows measured
    again), the warm-up's other frames none. The tracking stays as accurate as without the
    setting on this global-shutter clip, and invalid settings stop the tracker before any
    frame."""
    from test_tracker import INTR, ate_cm, sequence, small_cfg
    for key, value in (("rolling_shutter_ms", -1.0), ("rolling_shutter_stamp_row", 1.5)):
        cfg = small_cfg()
        setattr(cfg.camera, key, value)
        with pytest.raises(TrackingError, match=key):
            Tracker(cfg, INTR)
    frames, gt = sequence(40)
    ates = {}
    for ms in (0.0, 1.0):
        cfg = small_cfg()
        cfg.camera.rolling_shutter_ms, cfg.camera.rolling_shutter_stamp_row = ms, 1.0
        trk = Tracker(cfg, INTR)
        for f in frames:
            trk.track(f)
        assert trk.initialized and trk.n_lost == 0
        ts, poses = trk.trajectory_full()
        ates[ms] = ate_cm(frames, gt, ts, poses)
    warm = sorted(trk.kfs[k].frame_index for k in trk.published)[:cfg.tracking.init_min_keyframes]
    assert warm[0] == 0 and all(trk._rs_motion[i] is not None for i in warm)
    assert trk._rs_motion[1] is None and not trk._rs_raw
    late = {i: m for i, m in trk._rs_motion.items() if i >= 20}
    assert len(late) == 20 and all(m is not None and np.isfinite(m.omega).all() and m.depth > 0
                                   for m in late.values())
    # the motion model's angular velocity is the clip's (of the frame before: smooth motion)
    true = {i: angular_velocity(gt[i - 1][:3, :3].T @ gt[i][:3, :3], 1 / 30.0) for i in late}
    # (a sign or frame error would be off by about twice the magnitude; a frame's pose noise
    # makes about half of this slow turn, 0.09 rad/s: 0.1 px over a 20 ms readout)
    err = np.median([np.linalg.norm(late[i].omega - true[i]) for i in true])
    assert err < 0.6 * np.median([np.linalg.norm(w) for w in true.values()])
    cos = [late[i].omega @ true[i] / np.linalg.norm(late[i].omega) / np.linalg.norm(true[i])
           for i in true]
    assert np.median(cos) > 0.8
    assert ates[1.0] < 1.5 * ates[0.0] + 0.05
