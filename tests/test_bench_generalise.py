"""The generalisation benchmark's DSO adapter and suite definition (no DSO here: a stand-in
executable that reads DSO's inputs and writes DSO's result file)."""
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
import bench_generalise as bg                    # noqa: E402
sys.path.remove(str(REPO / "benchmarks"))

from splat_slam_ros.io.trajectory_io import read_trajectory   # noqa: E402


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen") / "seq"
    subprocess.run([sys.executable, "-m", "splat_slam_synth.cli", "--frames", "12",
                    "--size", "96x72", "--out", str(out), "--quiet"], check=True,
                   capture_output=True, timeout=120)
    return out


FAKE_DSO = textwrap.dedent('''\
    #!{python}
    # Stands in for dso_dataset: checks the call and the calibration file, then "tracks"
    # every frame but the first three by writing the ground truth as DSO's result.txt.
    import sys
    from pathlib import Path
    args = dict(a.split("=", 1) for a in sys.argv[1:])
    assert args["mode"] == "1" and args["nogui"] == "1", args
    cam = Path(args["calib"]).read_text().split("\\n")
    assert cam[0].startswith("Pinhole ") and cam[2] == "crop", cam
    imgs = sorted(Path(args["files"]).iterdir())
    times = [l.split() for l in Path("times.txt").read_text().splitlines()]
    assert [t[0] for t in times] == [p.stem for p in imgs]
    gt = {{}}
    for line in (imgs[0].resolve().parent.parent / "groundtruth.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            v = line.split()
            gt[round(float(v[0]), 4)] = v[1:]
    with open("result.txt", "w") as fh:
        for name, t in times[3:]:
            fh.write(t + " " + " ".join(gt[round(float(t), 4)]) + "\\n")
''')


def test_dso_adapter_runs_the_binary_on_the_same_frames_and_scores_its_result(small_seq,
                                                                               tmp_path):
    fake = tmp_path / "dso_dataset"
    fake.write_text(FAKE_DSO.format(python=sys.executable))
    fake.chmod(0o755)
    r = bg.run_dso(fake, small_seq)
    assert r["rc"] == 0 and r["frames"] == 12 and r["posed"] == 9
    assert r["ate_full_cm"] == pytest.approx(0.0, abs=1e-3)      # its poses were exact
    assert r["fps"] > 0 and r["peak_rss_mb"] >= 0


def test_dso_that_writes_nothing_counts_no_posed_frames(small_seq, tmp_path):
    fake = tmp_path / "dso_dataset"
    fake.write_text(f"#!{sys.executable}\nimport sys\nsys.exit(1)\n")
    fake.chmod(0o755)
    r = bg.run_dso(fake, small_seq)
    assert r["rc"] == 1 and r["posed"] == 0 and r["ate_full_cm"] is None


def test_camera_file_is_dso_pinhole_in_relative_units(small_seq, tmp_path):
    _img, cam, stamps, (gt_ts, _gt) = bg.dso_inputs(small_seq, tmp_path)
    first, size = cam.read_text().splitlines()[:2]
    fx, fy, cx, cy = map(float, first.split()[1:5])
    K = read_intrinsics(small_seq)
    assert size == f"{K['width']} {K['height']}"
    assert fx * K["width"] == pytest.approx(K["fx"]) and cy * K["height"] == \
        pytest.approx(K["cy"] + 0.5)
    assert np.allclose(stamps, gt_ts)


def read_intrinsics(seq: Path) -> dict:
    import yaml
    return yaml.safe_load((seq / "intrinsics.yaml").read_text())


def test_suite_covers_every_trajectory_scene_rate_and_keeps_check_apart():
    gen = [c for c in bg.SUITE.values() if "real" not in c]
    trajs = {p.name for p in (REPO.parent / "shared" / "data" / "trajectories").glob("*")}
    if trajs:
        assert {c["traj"] for c in gen} == trajs
    assert {c["scene"] for c in gen} == {"room", "low_texture", "tiled", "repetitive", "thin",
                                         "deep"}
    assert {c["fps"] for c in gen} == {20, 30}
    assert {c["realism"] for c in gen} == {"realistic", "harsh"}
    tune = [c for c in gen if c["split"] == "tuning"]
    check = [c for c in gen if c["split"] == "check"]
    assert tune and check and not {c["seed"] for c in tune} & {c["seed"] for c in check}
    assert any(c.get("real") and c["split"] == "check" for c in bg.SUITE.values())
    assert all(n.startswith(c["split"][0] + "_") for n, c in bg.SUITE.items())


def test_unknown_case_and_bad_override_exit_2(capsys):
    assert bg.main(["--cases", "nope"]) == 2
    assert "unknown case" in capsys.readouterr().err
    assert bg.main(["--cases", "c_euroc_v101_real", "--set", "tracking.nope=1"]) == 2
    assert "nope" in capsys.readouterr().err
