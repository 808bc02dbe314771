import numpy as np
import pytest
import torch

from splat_slam_ros import geometry as g
from splat_slam_ros.io.trajectory_io import TrajectoryFormatError, detect_format, read_trajectory, write_tum


def _random_poses(n, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return g.se3_exp(torch.randn(n, 6, generator=gen, dtype=torch.float64) * 0.5).numpy()


def test_tum_roundtrip(tmp_path):
    P = _random_poses(10)
    ts = np.arange(10) * 0.033 + 1305031098.6659
    write_tum(tmp_path / "t.txt", ts, P)
    ts2, P2 = read_trajectory(tmp_path / "t.txt")
    assert detect_format(tmp_path / "t.txt") == "tum"
    assert np.allclose(ts2, ts, atol=1e-6) and np.allclose(P2, P, atol=1e-8)


def test_kitti_and_euroc(tmp_path):
    P = _random_poses(4, 1)
    (tmp_path / "k.txt").write_text("\n".join(" ".join(f"{x:.12e}" for x in T[:3].ravel()) for T in P))
    ts, P2 = read_trajectory(tmp_path / "k.txt")
    assert detect_format(tmp_path / "k.txt") == "kitti" and np.allclose(P2, P) and np.allclose(ts, [0, .1, .2, .3])
    tq = g.pose_to_tq(torch.from_numpy(P)).numpy()
    rows = ["#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z"]
    for i, r in enumerate(tq):
        rows.append(f"{1403715524907143168 + i * 5000000}," + ",".join(
            f"{x:.12f}" for x in [*r[:3], r[6], r[3], r[4], r[5], 0.1, 0.2]))
    (tmp_path / "e.csv").write_text("\n".join(rows))
    ts, P3 = read_trajectory(tmp_path / "e.csv")
    assert detect_format(tmp_path / "e.csv") == "euroc"
    assert np.allclose(P3, P, atol=1e-9) and np.allclose(np.diff(ts), 0.005, rtol=0, atol=1e-6)


def test_real_trajectories(shared_data):
    d = shared_data / "trajectories"
    ts, P = read_trajectory(d / "freiburg1_xyz-groundtruth.txt")
    assert len(ts) == 3000 and 29 < ts[-1] - ts[0] < 31
    ts, P = read_trajectory(d / "V102_groundtruth.csv")
    assert np.all(np.diff(ts) > 0)
    ts, P = read_trajectory(d / "KITTI_00_gt.txt")
    assert P.shape == (4541, 4, 4)


@pytest.mark.parametrize("text,msg", [
    ("", "empty trajectory"),
    ("1 2 3\n", "cannot tell the format"),
    ("1 2 3 4 5 6 7 x\n", "not a numeric trajectory row"),
    ("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0\n", "cannot tell|different numbers of columns|need 8"),
    ("1 0 0 0 0 0 0 5\n", "not unit length"),
])
def test_bad_files(file_error, text, msg):
    file_error("bad.txt", text, read_trajectory, TrajectoryFormatError, msg)


def test_missing_file(tmp_path):
    with pytest.raises(TrajectoryFormatError, match="not found"):
        read_trajectory(tmp_path / "none.txt")
