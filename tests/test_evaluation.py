"""Tests for splat_slam_ros.evaluation and the splat-slam-eval CLI.

Trajectory metrics are checked against closed-form answers and against the evo library
(the reference evaluation's tool) on a real TUM ground-truth trajectory.
"""
from __future__ import annotations

import copy
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from splat_slam_ros.evaluation import depth as evd
from splat_slam_ros.evaluation import image as evm
from splat_slam_ros.evaluation import inputs as evi
from splat_slam_ros.evaluation import perceptual as evp
from splat_slam_ros.evaluation import trajectory as evt
from splat_slam_ros.cli.eval import main as eval_main
from splat_slam_ros.geometry import apply_sim3_to_poses, so3_exp
from splat_slam_ros.io.trajectory_io import read_trajectory, write_tum
from conftest import FrameList

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# the tests build TorchScript backbones themselves; torch 2.13 flags torch.jit as deprecated
pytestmark = pytest.mark.filterwarnings("ignore:.*torch.jit.*:DeprecationWarning")

FR1 = DATA / "trajectories" / "freiburg1_xyz-groundtruth.txt"
KITTI = DATA / "trajectories" / "KITTI_00_gt.txt"


def _fr1():
    if not FR1.is_file():
        pytest.skip(f"shared data not found: {FR1}")
    return read_trajectory(FR1)


def _random_sim3(rng, scale):
    R = so3_exp(torch.as_tensor(rng.normal(0, 1.0, 3)))
    t = torch.as_tensor(rng.normal(0, 2.0, 3))
    return scale, R, t


def _transform(P, s, R, t):
    return apply_sim3_to_poses(s, R, t, torch.from_numpy(P)).numpy()


def _perturb_rotations(P, rng, sigma):
    out = P.copy()
    dR = so3_exp(torch.as_tensor(rng.normal(0, sigma, (len(P), 3)))).numpy()
    out[:, :3, :3] = out[:, :3, :3] @ dR
    return out


def _synthetic_traj(n=200, seed=0):
    """A smooth non-planar trajectory (helix) with rotating orientation."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0, 4 * np.pi, n)
    pos = np.stack([np.cos(s), np.sin(s), 0.1 * s], 1) + rng.normal(0, 1e-3, (n, 3))
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, :3] = so3_exp(torch.as_tensor(np.stack([0.1 * s, 0.05 * s, s], 1))).numpy()
    P[:, :3, 3] = pos
    return np.arange(n) * 0.05 + 100.0, P


def _evo_traj(ts, P):
    from evo.core.trajectory import PoseTrajectory3D
    return PoseTrajectory3D(poses_se3=list(P), timestamps=np.asarray(ts, dtype=np.float64))


# ----------------------------------------------------------------- Umeyama
@pytest.mark.parametrize("with_scale", [True, False])
def test_umeyama_matches_evo(with_scale):
    from evo.core.geometry import umeyama_alignment as evo_umeyama
    rng = np.random.default_rng(3)
    src = rng.normal(0, 1, (50, 3))
    s0, R0, t0 = _random_sim3(rng, 0.37)
    dst = s0 * src @ R0.numpy().T + t0.numpy() + rng.normal(0, 0.05, (50, 3))
    s, R, t = evt.umeyama_alignment(src, dst, with_scale=with_scale)
    r_e, t_e, c_e = evo_umeyama(src.T, dst.T, with_scale)
    assert abs(s - c_e) < 1e-10
    np.testing.assert_allclose(R, r_e, atol=1e-10)
    np.testing.assert_allclose(t, t_e, atol=1e-10)
    assert abs(np.linalg.det(R) - 1) < 1e-10
    if with_scale:
        assert abs(s - 0.37) < 0.01
    else:
        assert s == 1.0


def test_umeyama_returns_rotation_not_reflection():
    rng = np.random.default_rng(4)
    src = rng.normal(0, 1, (30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])          # mirror image: best proper rotation
    _, R, _ = evt.umeyama_alignment(src, dst)
    assert abs(np.linalg.det(R) - 1) < 1e-10


def test_umeyama_degenerate_inputs():
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 3.0])
    with pytest.raises(evi.MetricError, match="collinear"):
        evt.umeyama_alignment(line, line + 1)
    with pytest.raises(evi.MetricError, match="at least 3"):
        evt.umeyama_alignment(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(evi.MetricError, match="equal shape"):
        evt.umeyama_alignment(np.zeros((5, 3)), np.zeros((4, 3)))


# --------------------------------------------------------------------- ATE
@pytest.mark.parametrize("scale", [0.25, 1.0, 3.7])
def test_ate_of_sim3_transformed_copy_is_zero_and_scale_recovered(scale):
    ts, P = _fr1()
    s, R, t = _random_sim3(np.random.default_rng(int(scale * 10)), scale)
    E = _transform(P, s, R, t)
    r = evt.ate(ts, P, ts, E, align="sim3")
    assert r["rmse_cm"] < 1e-8 and r["max_cm"] < 1e-8
    assert r["n_matched"] == len(ts)
    assert abs(r["scale"] - 1.0 / scale) < 1e-9
    assert r["rot_rmse_deg"] < 1e-6
    np.testing.assert_allclose(r["aligned_est_poses"], P, atol=1e-9)
    # SE(3) alignment cannot undo a scale change, Sim(3) can
    if scale != 1.0:
        assert evt.ate(ts, P, ts, E, align="se3")["rmse_cm"] > 1.0


def test_ate_known_offset_without_alignment():
    ts, P = _synthetic_traj()
    rng = np.random.default_rng(5)
    d = rng.normal(size=(len(P), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    E = P.copy()
    E[:, :3, 3] += 0.037 * d                         # 3.7 cm in random directions
    r = evt.ate(ts, P, ts, E, align="none")
    for k in ("rmse_cm", "mean_cm", "median_cm", "min_cm", "max_cm"):
        assert abs(r[k] - 3.7) < 1e-9, k
    assert r["std_cm"] < 1e-9 and r["scale"] == 1.0


def test_ate_sim3_and_se3_closed_form():
    """est = gt + e with e zero-mean and orthogonal to the centred gt coordinates.

    Then the cross-covariance is the (symmetric PD) gt covariance, so the optimal rotation
    is I; with A = trace(gt covariance) and B = mean |e|^2, SE(3) gives rmse = sqrt(B) and
    Sim(3) shrinks by c = A / (A + B), giving rmse = sqrt(A B / (A + B)).
    """
    ts, P = _fr1()
    rng = np.random.default_rng(6)
    y = P[:, :3, 3]
    e = rng.normal(0, 0.05, y.shape)
    basis, _ = np.linalg.qr(np.concatenate([np.ones((len(y), 1)), y], 1))
    e -= basis @ (basis.T @ e)                        # remove mean and gt-correlated part
    E = P.copy()
    E[:, :3, 3] = y + e
    yc = y - y.mean(0)
    A = float((yc ** 2).sum(1).mean())
    B = float((e ** 2).sum(1).mean())
    r3 = evt.ate(ts, P, ts, E, align="se3")
    assert abs(r3["rmse_cm"] - 100 * np.sqrt(B)) < 1e-8
    np.testing.assert_allclose(r3["rotation"], np.eye(3), atol=1e-9)
    rs = evt.ate(ts, P, ts, E, align="sim3")
    assert abs(rs["scale"] - A / (A + B)) < 1e-10
    assert abs(rs["rmse_cm"] - 100 * np.sqrt(A * B / (A + B))) < 1e-8
    assert rs["rmse_cm"] < r3["rmse_cm"]


def test_ate_matches_evo_on_real_trajectory():
    from evo.core import metrics, sync
    ts, P = _fr1()
    rng = np.random.default_rng(7)
    s, R, t = _random_sim3(rng, 0.6)
    E = _transform(_perturb_rotations(P, rng, 0.01), s, R, t)
    E[:, :3, 3] += rng.normal(0, 0.01, (len(E), 3)) + np.cumsum(rng.normal(0, 5e-4, (len(E), 3)), 0)
    keep = np.sort(rng.choice(len(ts), 900, replace=False))
    est_ts = ts[keep] + rng.uniform(-0.004, 0.004, len(keep))   # jitter < half the 100 Hz period
    E = E[keep]
    for align in ("sim3", "se3"):
        r = evt.ate(ts, P, est_ts, E, align=align, max_diff=0.02)
        ref, est = sync.associate_trajectories(_evo_traj(ts, P), _evo_traj(est_ts, E),
                                               max_diff=0.02)
        est = copy.deepcopy(est)
        r_a, t_a, s_a = est.align(ref, correct_scale=(align == "sim3"))
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((ref, est))
        st = ape.get_all_statistics()
        assert r["n_matched"] == ref.num_poses == 900
        for k in ("rmse", "mean", "median", "std", "min", "max"):
            assert abs(r[f"{k}_cm"] - 100 * st[k]) < 1e-6, (align, k)
        assert abs(r["scale"] - s_a) < 1e-9
        np.testing.assert_allclose(r["aligned_est_poses"], np.stack(est.poses_se3), atol=1e-9)
        assert r["rmse_cm"] > 0.5                  # the test is not trivially zero


def test_ate_requires_three_associated_poses_and_names_ranges():
    ts, P = _synthetic_traj(50)
    with pytest.raises(evi.MetricError) as ei:
        evt.ate(ts, P, ts + 1000.0, P)
    msg = str(ei.value)
    assert "only 0 poses associate" in msg
    assert "100.000000" in msg and "1100.000000" in msg      # both timestamp ranges
    with pytest.raises(evi.MetricError, match="only 2 poses"):
        evt.ate(ts, P, ts[:2], P[:2])


def test_ate_input_errors():
    ts, P = _synthetic_traj(20)
    with pytest.raises(evi.MetricError, match="unknown alignment"):
        evt.ate(ts, P, ts, P, align="sim4")
    with pytest.raises(evi.MetricError, match=r"\(N, 4, 4\)"):
        evt.ate(ts, P[:, :3, 3], ts, P)
    with pytest.raises(evi.MetricError, match="timestamps but"):
        evt.ate(ts[:-1], P, ts, P)
    bad = P.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(evi.MetricError, match="non-finite"):
        evt.ate(ts, P, ts, bad)


def test_ate_accepts_torch_inputs():
    ts, P = _synthetic_traj(30)
    r = evt.ate(torch.from_numpy(ts), torch.from_numpy(P), ts, P)
    assert r["rmse_cm"] < 1e-8


# ------------------------------------------------------------- association
def test_associate_with_offset_missing_and_unsorted_stamps():
    rng = np.random.default_rng(8)
    a = np.arange(300) * 0.033 + 50.0
    sub = np.sort(rng.choice(300, 120, replace=False))
    b = a[sub] + 100.0 + rng.uniform(-0.01, 0.01, len(sub))       # clock offset + jitter
    perm = rng.permutation(len(b))                               # unsorted input
    ia, ib = evt.associate(a, b[perm], max_diff=0.012, offset=-100.0)
    np.testing.assert_array_equal(ia, sub)
    np.testing.assert_array_equal(perm[ib], np.arange(len(sub)))
    # without the offset nothing matches
    assert len(evt.associate(a, b, max_diff=0.012)[0]) == 0


def test_associate_is_one_to_one_and_nearest():
    a = np.array([0.0, 1.0, 2.0])
    b = np.array([0.99, 1.005, 1.02, 5.0])
    ia, ib = evt.associate(a, b, max_diff=0.02)
    np.testing.assert_array_equal(ia, [1])
    np.testing.assert_array_equal(ib, [1])                       # the nearest, only once
    # two a stamps competing for one b: the closer wins, the other stays unmatched
    ia, ib = evt.associate(np.array([1.0, 1.015]), np.array([1.012]), max_diff=0.02)
    np.testing.assert_array_equal(ia, [1])
    np.testing.assert_array_equal(ib, [0])
    assert len(evt.associate([], b)[0]) == 0
    with pytest.raises(evi.MetricError, match="max_diff"):
        evt.associate(a, b, max_diff=-1)


def test_associate_agrees_with_evo_on_real_stamps():
    from evo.core.sync import matching_time_indices
    ts, _ = _fr1()
    rng = np.random.default_rng(9)
    # jitter below half the smallest GT spacing (7.7 ms): nearest matching is unambiguous
    est = np.sort(rng.choice(ts, 700, replace=False)) + rng.uniform(-0.003, 0.003, 700)
    ia, ib = evt.associate(ts, est, max_diff=0.02)
    ie, ig = matching_time_indices(est, ts, max_diff=0.02)
    assert len(ia) == 700
    assert sorted(zip(ig, ie)) == list(zip(ia.tolist(), ib.tolist()))
    # larger jitter: evo may map two estimates onto one GT stamp, ours stays one-to-one
    est = np.sort(rng.choice(ts, 700, replace=False)) + rng.uniform(-0.008, 0.008, 700)
    ia, ib = evt.associate(ts, est, max_diff=0.02)
    assert len(set(ia.tolist())) == len(ia) == len(set(ib.tolist()))
    assert np.all(np.abs(ts[ia] - est[ib]) <= 0.02)
    assert len(ia) >= 690


# --------------------------------------------------------------------- RPE
@pytest.mark.parametrize("delta,unit,all_pairs", [(1, "frames", False), (5, "frames", False),
                                                   (3, "frames", True), (0.1, "meters", False)])
def test_rpe_matches_evo(delta, unit, all_pairs):
    from evo.core import metrics
    ts, P = _fr1()
    rng = np.random.default_rng(10)
    s, R, t = _random_sim3(rng, 1.8)
    E = _transform(_perturb_rotations(P, rng, 0.005), s, R, t)
    E[:, :3, 3] += rng.normal(0, 0.004, (len(E), 3))
    r = evt.rpe(ts, P, ts, E, delta=delta, unit=unit, align="sim3", all_pairs=all_pairs)
    ref, est = _evo_traj(ts, P), _evo_traj(ts, E)
    est.align(ref, correct_scale=True)
    evo_unit = metrics.Unit.frames if unit == "frames" else metrics.Unit.meters
    for rel, key, f in ((metrics.PoseRelation.translation_part, "trans", 100.0),
                        (metrics.PoseRelation.rotation_angle_deg, "rot", 1.0)):
        m = metrics.RPE(rel, delta, evo_unit, all_pairs=all_pairs)
        m.process_data((ref, est))
        st = m.get_all_statistics()
        unit_sfx = "cm" if key == "trans" else "deg"
        assert r["n_pairs"] == len(m.error)
        for k in ("rmse", "mean", "median", "std", "max"):
            assert abs(r[f"{key}_{k}_{unit_sfx}"] - f * st[k]) < 1e-6, (key, k)
    assert r["trans_rmse_cm"] > 0.1 and r["rot_rmse_deg"] > 0.1


def test_rpe_scale_alignment_and_errors():
    ts, P = _synthetic_traj(100)
    E = _transform(P, 2.0, torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64))
    assert evt.rpe(ts, P, ts, E, align="sim3")["trans_rmse_cm"] < 1e-8
    # without alignment each relative translation is twice as long: error = |gt step|
    r = evt.rpe(ts, P, ts, E, align="none")
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    assert abs(r["trans_mean_cm"] - 100 * steps.mean()) < 1e-8
    assert r["rot_max_deg"] < 1e-6
    with pytest.raises(evi.MetricError, match="no pose pairs"):
        evt.rpe(ts, P, ts, P, delta=500)
    with pytest.raises(evi.MetricError, match="positive integer"):
        evt.rpe(ts, P, ts, P, delta=1.5)
    with pytest.raises(evi.MetricError, match="unknown RPE unit"):
        evt.rpe(ts, P, ts, P, unit="seconds")


# --------------------------------------------------------------------- CLI
def _write_est(tmp_path, seed=11, scale=0.5):
    ts, P = _fr1()
    rng = np.random.default_rng(seed)
    s, R, t = _random_sim3(rng, scale)
    E = _transform(P, s, R, t)
    E[:, :3, 3] += rng.normal(0, 0.003, (len(E), 3))
    keep = np.arange(0, len(ts), 3)
    run = tmp_path / "run"
    write_tum(run / "trajectory_full.txt", ts[keep], E[keep])
    return ts, P, ts[keep], E[keep], run


def test_cli_prints_table_ate_line_json_and_plot(tmp_path, capsys):
    ts, P, ets, E, run = _write_est(tmp_path)
    out_json, out_png = tmp_path / "m.json", tmp_path / "p.png"
    rc = eval_main(["--gt", str(FR1), "--est", str(run), "--json", str(out_json),
                    "--plot", str(out_png)])
    out = capsys.readouterr().out
    assert rc == 0
    lines = [ln for ln in out.splitlines() if ln.startswith("ATE_RMSE_cm")]
    assert len(lines) == 1 and re.fullmatch(r"ATE_RMSE_cm \d+\.\d{4}", lines[0])
    # the CLI reads the 9-decimal TUM file, so compare with the file's numbers
    r_ets, r_E = read_trajectory(run / "trajectory_full.txt")
    expected = evt.ate(ts, P, r_ets, r_E)
    assert lines[0] == f"ATE_RMSE_cm {expected['rmse_cm']:.4f}"
    assert 0.1 < expected["rmse_cm"] < 2.0
    for word in ("matched poses", "scale", "ATE rmse", "ATE median", "ATE std", "ATE max",
                 "RPE trans rmse", "RPE rot rmse"):
        assert word in out, word
    d = json.loads(out_json.read_text())
    assert abs(d["ate"]["rmse_cm"] - expected["rmse_cm"]) < 1e-9
    assert d["ate"]["n_matched"] == len(ets)
    assert abs(d["ate"]["scale"] - 2.0) < 0.01
    assert d["rpe"]["trans_rmse_cm"] > 0 and "rot_rmse_deg" in d["rpe"]
    assert np.asarray(d["alignment"]["rotation"]).shape == (3, 3)
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out_png.stat().st_size > 10_000


def test_cli_align_none_and_kitti_format(tmp_path, capsys):
    if not KITTI.is_file():
        pytest.skip(f"shared data not found: {KITTI}")
    rc = eval_main(["--gt", str(KITTI), "--est", str(KITTI), "--gt-format", "kitti",
                    "--align", "none", "--json", str(tmp_path / "k.json")])
    assert rc == 0
    assert "ATE_RMSE_cm 0.0000" in capsys.readouterr().out.splitlines()
    assert json.loads((tmp_path / "k.json").read_text())["gt_format"] == "kitti"


@pytest.mark.parametrize("case", ["missing", "badformat", "noassoc", "emptydir", "gtdir"])
def test_cli_user_errors_exit_2(tmp_path, capsys, case):
    ts, P, ets, E, run = _write_est(tmp_path)
    gt, est = str(FR1), str(run)
    if case == "missing":
        est = str(tmp_path / "nope.txt")
    elif case == "badformat":
        bad = tmp_path / "bad.txt"
        bad.write_text("1 2 3 4 5\n6 7 8 9 10\n")
        est = str(bad)
    elif case == "noassoc":
        shifted = tmp_path / "shifted.txt"
        write_tum(shifted, ets + 5000.0, E)
        est = str(shifted)
    elif case == "emptydir":
        (tmp_path / "empty").mkdir()
        est = str(tmp_path / "empty")
    elif case == "gtdir":
        gt = str(tmp_path)
    rc = eval_main(["--gt", gt, "--est", est])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err
    if case == "noassoc":
        assert "ground-truth stamps" in err and "estimate stamps" in err


def test_cli_entry_point_subprocess(tmp_path):
    r = subprocess.run([sys.executable, "-m", "splat_slam_ros.cli.eval", "--gt",
                        str(tmp_path / "a.txt"), "--est", str(tmp_path / "b.txt")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.startswith("error: ") and "Traceback" not in r.stderr


# --------------------------------------------------------- image metrics
def _img(h=32, w=40, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.2, 0.8, (h // 4, w // 4, 3))
    return np.kron(base, np.ones((4, 4, 1)))          # blocky texture, values in [0.2, 0.8]


def test_psnr_known_value_mask_and_layouts():
    ref = _img()
    img = ref + 0.1
    assert abs(evm.psnr(img, ref) - 20.0) < 1e-9               # mse 0.01
    assert evm.psnr(ref, ref) == float("inf")
    noisy = ref.copy()
    noisy[:8] = 0.0
    mask = np.ones(ref.shape[:2], bool)
    mask[:8] = False
    assert evm.psnr(noisy, ref, mask=mask) == float("inf")
    assert evm.psnr(noisy, ref) < 20
    # CHW torch and uint8 inputs give the same numbers
    t = torch.from_numpy(img).permute(2, 0, 1)
    assert abs(evm.psnr(t, torch.from_numpy(ref)) - 20.0) < 1e-9
    u8 = (ref * 255).round().astype(np.uint8)
    assert evm.psnr(u8, u8.astype(np.float64) / 255) == float("inf")
    with pytest.raises(evi.MetricError, match="shapes differ"):
        evm.psnr(ref, ref[:-1])
    with pytest.raises(evi.MetricError, match=r"\[0, 1\]"):
        evm.psnr(ref * 255, ref)
    with pytest.raises(evi.MetricError, match="no pixels"):
        evm.psnr(ref, ref, mask=np.zeros(ref.shape[:2], bool))


def test_exposure_compensation_recovers_affine():
    ref = _img()
    a = np.array([1.3, 0.8, 1.1])
    b = np.array([-0.05, 0.1, 0.02])
    img = (ref - b) / a                                          # a * img + b == ref
    assert evm.psnr(img, ref) < 30
    comp, a_hat, b_hat = evm.exposure_compensate(img, ref, return_params=True)
    np.testing.assert_allclose(a_hat, a, atol=1e-9)
    np.testing.assert_allclose(b_hat, b, atol=1e-9)
    assert evm.psnr(img, ref, exposure_compensation=True) > 150


def test_ssim_sanity():
    ref = _img(48, 48)
    rng = np.random.default_rng(1)
    assert abs(evm.ssim(ref, ref) - 1.0) < 1e-6
    s_small = evm.ssim(np.clip(ref + rng.normal(0, 0.02, ref.shape), 0, 1), ref)
    s_large = evm.ssim(np.clip(ref + rng.normal(0, 0.2, ref.shape), 0, 1), ref)
    assert 1.0 > s_small > s_large > 0.0
    with pytest.raises(evi.MetricError, match="at least 11x11"):
        evm.ssim(ref[:8, :8], ref[:8, :8])


def test_depth_l1_cm():
    ref = np.full((10, 12), 2.0, np.float32)
    d = ref + 0.05
    assert abs(evd.depth_l1_cm(d, ref) - 5.0) < 1e-4
    ref[0, :] = 0.0                                   # missing sensor depth
    ref[1, :] = np.nan
    d[2, :] = 0.0                                     # no rendered depth
    d[3, :] = 99.0
    m = np.ones_like(ref, bool)
    m[3] = False
    assert abs(evd.depth_l1_cm(d, ref, mask=m) - 5.0) < 1e-4
    assert evd.depth_l1_cm(d, ref) > 5.0
    with pytest.raises(evi.MetricError, match="no pixel"):
        evd.depth_l1_cm(np.zeros((4, 4)), np.ones((4, 4)))
    with pytest.raises(evi.MetricError, match="H x W"):
        evd.depth_l1_cm(np.ones((4, 4)), np.ones((4, 5)))


def test_depth_edge_band_marks_pixels_near_depth_discontinuities_only():
    ref = np.full((20, 30), 2.0, np.float32)
    ref[:, 15:] = 4.0                                 # a step between columns 14 and 15
    ref[:, :5] = np.linspace(2.0, 2.08, 5)            # a gentle slope (<5 % per pixel): no edge
    ref[0, 20] = 0.0                                  # a missing pixel is no edge either
    band = evd.depth_edge_band(ref, 3).numpy()
    cols = np.flatnonzero(band.any(0))
    assert cols.tolist() == list(range(11, 19)), cols  # 14, 15 and 3 px on either side
    assert band[:, 11:19].all()
    assert not evd.depth_edge_band(np.full((8, 8), 1.0), 2).any()
    assert evd.depth_edge_band(ref, 0).numpy().sum() == 2 * 20


# ------------------------------------------------------------------- LPIPS
class _TinyNet(torch.nn.Module):
    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.c1 = torch.nn.Conv2d(3, 6, 3, padding=1)
        self.c2 = torch.nn.Conv2d(6, 8, 3, stride=2, padding=1)

    def forward(self, x):
        f1 = torch.relu(self.c1(x))
        f2 = torch.relu(self.c2(f1))
        return [f1, f2]


class _BadNet(torch.nn.Module):
    def forward(self, x):
        return x.mean(1)                                 # (B, H, W): not feature maps


def _manual_lpips(net, img, ref, weights=None):
    x = torch.stack([torch.from_numpy(img), torch.from_numpy(ref)]).permute(0, 3, 1, 2)
    feats = net(x.float() * 2 - 1)
    total = 0.0
    for i, f in enumerate(feats):
        f = f.double()
        f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
        d = (f[0] - f[1]) ** 2
        if weights is not None:
            d = d * weights[i].double().view(-1, 1, 1)
        total += float(d.sum(0).mean())
    return total


@pytest.fixture
def lpips_files(tmp_path):
    net = _TinyNet().eval()
    path = tmp_path / "tiny.pt"
    torch.jit.save(torch.jit.script(net), str(path))
    return net, path


def test_lpips_identical_zero_and_monotone(lpips_files):
    net, path = lpips_files
    ref = _img(32, 32)
    rng = np.random.default_rng(2)
    noise = rng.normal(0, 1, ref.shape)
    assert evp.lpips(ref, ref, path) == 0.0
    d = [evp.lpips(np.clip(ref + s * noise, 0, 1), ref, path) for s in (0.02, 0.1, 0.3)]
    assert 0 < d[0] < d[1] < d[2]
    with torch.no_grad():
        expect = _manual_lpips(net, np.clip(ref + 0.1 * noise, 0, 1), ref)
    assert abs(d[1] - expect) < 1e-5 * max(1.0, expect)
    mean = evp.lpips(np.clip(ref + 0.1 * noise, 0, 1), ref, path, layer_reduce="mean")
    assert abs(mean - d[1] / 2) < 1e-9


def test_lpips_channel_weights_file_and_embedded(lpips_files, tmp_path):
    net, path = lpips_files
    ref = _img(32, 32)
    img = np.clip(ref + 0.1 * np.random.default_rng(3).normal(0, 1, ref.shape), 0, 1)
    w = [torch.rand(6), torch.rand(8)]
    wfile = tmp_path / "lin.pth"                          # official-LPIPS-style keys/shapes
    torch.save({f"lin{i}.model.1.weight": wi.view(1, -1, 1, 1) for i, wi in enumerate(w)}, wfile)
    with torch.no_grad():
        expect = _manual_lpips(net, img, ref, w)
    assert abs(evp.lpips(img, ref, path, weights_path=wfile) - expect) < 1e-5
    zeros = tmp_path / "zeros.pt"
    torch.save([torch.zeros(6), torch.zeros(8)], zeros)
    assert evp.lpips(img, ref, path, weights_path=zeros) == 0.0
    # weights carried inside the TorchScript module as buffers lpips_w<i>
    net2 = _TinyNet().eval()
    for i, wi in enumerate(w):
        net2.register_buffer(f"lpips_w{i}", wi.clone())
    p2 = tmp_path / "tiny_w.pt"
    torch.jit.save(torch.jit.script(net2), str(p2))
    assert abs(evp.lpips(img, ref, p2) - expect) < 1e-5


def test_lpips_accepts_torch_export_program(lpips_files, tmp_path):
    net, path = lpips_files
    dims = {2: torch.export.Dim("h", min=8, max=2048), 3: torch.export.Dim("w", min=8, max=2048)}
    ep = torch.export.export(net, (torch.zeros(2, 3, 32, 32),), dynamic_shapes=(dims,))
    p2 = tmp_path / "tiny.pt2"
    torch.export.save(ep, str(p2))
    ref = _img(32, 40)
    img = np.clip(ref + 0.1 * np.random.default_rng(4).normal(0, 1, ref.shape), 0, 1)
    d_export = evp.lpips(img, ref, p2)
    assert d_export > 0 and abs(d_export - evp.lpips(img, ref, path)) < 1e-6


def test_lpips_load_errors(lpips_files, tmp_path):
    _, path = lpips_files
    ref = _img(32, 32)
    with pytest.raises(evi.MetricError, match="not found"):
        evp.lpips(ref, ref, tmp_path / "missing.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"this is not a torchscript archive" * 10)
    with pytest.raises(evi.MetricError, match="TorchScript file .* nor a torch.export"):
        evp.lpips(ref, ref, corrupt)
    bad = tmp_path / "bad.pt"
    torch.jit.save(torch.jit.script(_BadNet()), str(bad))
    with pytest.raises(evi.MetricError, match="feature maps"):
        evp.lpips(ref, ref, bad)
    wrong = tmp_path / "wrong.pt"
    torch.save([torch.ones(6)], wrong)
    with pytest.raises(evi.MetricError, match="1 layers"):
        evp.lpips(ref, ref, path, weights_path=wrong)
    chans = tmp_path / "chans.pt"
    torch.save([torch.ones(5), torch.ones(8)], chans)
    with pytest.raises(evi.MetricError, match="5 weights for 6 channels"):
        evp.lpips(ref, ref, path, weights_path=chans)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x00garbage")
    with pytest.raises(evi.MetricError, match="weights file"):
        evp.lpips(ref, ref, path, weights_path=garbage)


def test_image_metrics_and_summarize(lpips_files):
    _, path = lpips_files
    ref = _img(32, 32)
    img = np.clip(ref * 0.9 + 0.05, 0, 1)                   # pure exposure change
    m = evm.image_metrics(img, ref, depth=np.full((32, 32), 1.0), ref_depth=np.full((32, 32), 1.02),
                         lpips_model=path)
    assert m["psnr"] > 100                                   # compensated away
    assert set(m) == {"psnr", "ssim", "lpips", "depth_l1_cm"}
    assert abs(m["depth_l1_cm"] - 2.0) < 1e-9
    s = evm.summarize([{"psnr": 20.0, "ssim": 0.5}, {"psnr": 30.0, "ssim": 0.7}])
    assert abs(s["psnr"] - 25.0) < 1e-12 and abs(s["ssim"] - 0.6) < 1e-12


# ------------------------------------------------------------------ map depth L1 (pipeline)
def test_map_depth_l1_compares_in_the_keyframes_camera(tmp_path, monkeypatch):
    """``evaluation.run.evaluate_map_depth`` brings the dataset's depth to the keyframes' camera
    (undistorted, cropped, resized) before comparing it with the map's render in that
    camera: a perfect map of a tilted plane seen by a strongly distorted camera scores
    ~0 cm, with and without ``camera.crop``."""
    import cv2
    from types import SimpleNamespace
    from splat_slam_ros.evaluation import run as run_eval
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.mapping.mapper import Mapper
    from splat_slam_ros.types import Intrinsics
    K = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120, "plumb_bob", [-0.3, 0.1, 0.0, 0.0, 0.0])

    def plane_depth(xn, tx):                      # world plane z = 2 + 0.5 x, camera at x = tx
        return (2.0 + 0.5 * tx) / (1.0 - 0.5 * xn)

    v, u = np.mgrid[0:K.height, 0:K.width].astype(np.float64)
    und = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), K.K,
                              np.asarray(K.distortion)).reshape(K.height, K.width, 2)
    ts = np.arange(4) * 0.1
    poses = np.stack([np.eye(4)] * 4)
    poses[:, 0, 3] = [0.0, 0.05, 0.05, 0.0]        # a square in x, y (the plane: no y term)
    poses[:, 1, 3] = [0.0, 0.0, 0.05, 0.05]
    frames = [SimpleNamespace(timestamp=t, gt_depth=plane_depth(und[..., 0], P[0, 3])
                              .astype(np.float32)) for t, P in zip(ts, poses)]
    class Data(FrameList):
        intrinsics, has_gt_depth = K, True

        def gt_trajectory(self):
            return ts, poses
    ds = Data(frames)

    class PlaneMap:                               # renders the plane exactly in its camera
        def __init__(self, intr):
            self.intr = intr

        def render(self, T):
            i = self.intr
            vv, uu = np.mgrid[0:i.height, 0:i.width].astype(np.float64)
            return None, plane_depth((uu - i.cx) / i.fx, T[0, 3]).astype(np.float32)

    monkeypatch.setattr(Mapper, "load_ply", staticmethod(lambda path, cfg, intr: PlaneMap(intr)))
    write_tum(tmp_path / "trajectory_keyframes.txt", ts, poses)
    (tmp_path / "map.ply").write_bytes(b"")
    for crop in (0, 8):
        cfg = SlamConfig()
        cfg.camera.crop = crop
        m = {}
        run_eval.evaluate_map_depth(ds, tmp_path, cfg, m)
        assert m.get("depth_l1_views") == 4 and m["depth_l1_cm"] < 0.5, (crop, m)


def test_map_depth_l1_is_split_into_depth_edges_and_surfaces(tmp_path, monkeypatch):
    """metrics.json says where the map's depth error is: a map that is exact except that the
    near surface bleeds 3 px onto the far one behind a depth step has all its error within
    one BA cell of the true edge (``depth_l1_edges_cm``) and none on the surfaces."""
    from types import SimpleNamespace
    from splat_slam_ros.evaluation import run as run_eval
    from splat_slam_ros.config import SlamConfig
    from splat_slam_ros.mapping.mapper import Mapper
    from splat_slam_ros.types import Intrinsics
    K = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    u = (np.arange(K.width) - K.cx) / K.fx
    step = np.where(u < 0, 1.0, 3.0).astype(np.float32)            # near left, far right
    ts = np.arange(4) * 0.1
    poses = np.stack([np.eye(4)] * 4)            # (the renders and depths ignore the poses,
    poses[:, 0, 3] = [0.0, 0.05, 0.05, 0.0]      # which only set the Sim(3) scale: 1)
    poses[:, 1, 3] = [0.0, 0.0, 0.05, 0.05]
    ds_frames = [SimpleNamespace(timestamp=t, gt_depth=np.tile(step, (K.height, 1)))
                 for t in ts]

    class Data(FrameList):
        intrinsics, has_gt_depth = K, True

        def gt_trajectory(self):
            return ts, poses

    class BleedingMap:
        def __init__(self, intr):
            self.intr = intr

        def render(self, T):
            i = self.intr
            x = (np.arange(i.width) - i.cx) / i.fx
            row = np.where(x < 3.0 / i.fx, 1.0, 3.0).astype(np.float32)   # 3 px too wide
            return None, np.tile(row, (i.height, 1))

    monkeypatch.setattr(Mapper, "load_ply",
                        staticmethod(lambda path, cfg, intr: BleedingMap(intr)))
    write_tum(tmp_path / "trajectory_keyframes.txt", ts, poses)
    (tmp_path / "map.ply").write_bytes(b"")
    m = {}
    run_eval.evaluate_map_depth(Data(ds_frames), tmp_path, SlamConfig(), m)
    assert m["depth_l1_views"] == 4 and m["depth_l1_cm"] > 1.0, m
    assert m["depth_l1_surfaces_cm"] == 0.0, m
    # 3 of the band's 2 x 8 + 2 columns are 200 cm off
    band = m["depth_edge_band_fraction"]
    assert 0.05 < band < 0.2, m
    assert m["depth_l1_edges_cm"] == pytest.approx(200.0 * 3 / 18, rel=0.2), m
    assert m["depth_l1_cm"] == pytest.approx(band * m["depth_l1_edges_cm"], rel=1e-3), m
