"""The generalisation benchmark's peers and suite definition: the DSO and ORB-SLAM3 adapters
(stand-in executables that read a peer's inputs and write its result file; the real peers are
on-demand) and the ORB vocabulary that ORB-SLAM3 reads."""
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
import bench_generalise as bg                    # noqa: E402
import orb_peer as op                            # noqa: E402
sys.path.remove(str(REPO / "benchmarks"))

from conftest import synth_sequence                                # noqa: E402
from splat_slam_ros.io.trajectory_io import read_trajectory   # noqa: E402


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory):
    return synth_sequence(tmp_path_factory.mktemp("gen") / "seq", 12, "96x72")


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


def run_peer(peer: str, script: str, seq: Path, tmp_path: Path) -> dict:
    """``peer``'s adapter on ``seq`` with ``script`` standing in for its executable (DSO's
    dso_dataset, or the python of ORB-SLAM3's scratch environment)."""
    fake = tmp_path / ("dso_dataset" if peer == "dso" else "python")
    fake.write_text(script)
    fake.chmod(0o755)
    if peer == "dso":
        return bg.run_dso(fake, seq)
    vocab = tmp_path / "voc.txt"
    vocab.write_text("10 5 0 0\n0 1 " + " ".join(["0"] * 32) + " 0.0")
    return bg.run_orbslam3(fake, vocab, seq)


@pytest.mark.parametrize("peer", ["dso", "orbslam3"])
def test_a_peer_runs_on_the_same_frames_and_is_scored_on_what_it_posed(peer, small_seq,
                                                                       tmp_path):
    stand_in = FAKE_DSO if peer == "dso" else FAKE_ORB_PYTHON
    r = run_peer(peer, stand_in.format(python=sys.executable), small_seq, tmp_path)
    assert r["rc"] == 0 and r["frames"] == 12 and r["posed"] == 9
    assert r["ate_full_cm"] == pytest.approx(0.0, abs=1e-3)      # its poses were exact
    assert r["fps"] > 0 and r["peak_rss_mb"] >= 0


@pytest.mark.parametrize("peer", ["dso", "orbslam3"])
def test_a_peer_that_fails_counts_no_posed_frames(peer, small_seq, tmp_path):
    r = run_peer(peer, f"#!{sys.executable}\nimport sys\nsys.exit(3)\n", small_seq, tmp_path)
    assert r["rc"] == 3 and r["posed"] == 0 and r["ate_full_cm"] is None


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
    assert {c["fps"] for c in gen} == {15, 20, 30}
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


def test_bad_starts_exit_2(capsys):
    assert bg.main(["--cases", "c_euroc_v101_real", "--starts", "0"]) == 2
    assert "--starts 0" in capsys.readouterr().err
    assert bg.main(["--cases", "c_euroc_v101_real", "--starts", "4", "--start-step", "10"]) == 2
    assert "below 30" in capsys.readouterr().err


def test_a_run_from_a_later_start_frame_tracks_the_frames_after_it(small_seq, tmp_path):
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import bench_tracking as bt
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    first = bt.run_case("s0", small_seq, {}, "", tmp_path)
    later = bt.run_case("s4", small_seq, {}, "", tmp_path, start_frame=4)
    assert first["frames"] == 12 and later["frames"] == 8


def _run(start, ate, posed=10, lost=0):
    return dict(start_frame=start, ate_full_cm=ate, posed=posed, frames=10, lost=lost,
                keyframes=3, fps=20.0)


def test_over_starts_keeps_the_median_run_and_the_range():
    r = bg.over_starts([_run(0, 5.0), _run(2, None, posed=4, lost=6), _run(4, 1.0)])
    assert r["start_frame"] == 0 and r["ate_full_cm"] == 5.0     # never initialised: worst
    assert [x["start_frame"] for x in r["starts"]] == [0, 2, 4]
    assert bg.ate_cell(r) == "5.000 (1.000-no ATE)"
    assert not bg.all_posed(r)                                   # one start lost frames
    r = bg.over_starts([_run(0, 2.0), _run(2, 1.0), _run(4, 3.0), _run(6, 4.0)])
    assert r["ate_full_cm"] == 2.0 and bg.ate_cell(r) == "2.000 (1.000-4.000)"
    assert bg.all_posed(r) and bg.ate_cell(_run(0, 1.5)) == "1.500"
    assert bg.ate_cell(bg.over_starts([_run(0, None), _run(2, None)])) == "-"


# ------------------------------------------------------------------ ORB-SLAM3 beside us
FAKE_ORB_PYTHON = textwrap.dedent('''\
    #!{python}
    # Stands in for the scratch environment's python running orb_peer.py JOB: checks the
    # job and its settings, then "tracks" every frame but the first three by writing the
    # ground truth as ORB-SLAM3's EuRoC trajectory (stamps in ns).
    import json, sys
    from pathlib import Path
    assert sys.argv[1].endswith("orb_peer.py"), sys.argv
    job = json.loads(Path(sys.argv[2]).read_text())
    st = Path(job["settings"]).read_text()
    assert st.startswith("%YAML:1.0") and "Camera.fx: " in st and "Camera.RGB: 1" in st, st
    assert Path(job["vocab"]).is_file() and len(job["images"]) == len(job["stamps"])
    seq = Path(job["images"][0]).resolve().parent.parent
    gt = {{}}
    for line in (seq / "groundtruth.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            v = line.split()
            gt[round(float(v[0]), 4)] = v[1:]
    with open(job["out"], "w") as fh:
        for t in job["stamps"][3:]:
            fh.write(f"{{int(round(t * 1e9))}} " + " ".join(gt[round(t, 4)]) + "\\n")
''')


def _parse_dbow2(path: Path):
    head, *rows = path.read_text().split("\n")
    k, L, scoring, weighting = map(int, head.split())
    nodes = [tuple(r.split()) for r in rows]
    return (k, L, scoring, weighting), nodes


def test_trained_vocabulary_is_dbow2_text_that_orbslam3_reads(tmp_path):
    rng = np.random.default_rng(0)
    # three "images": descriptors around three distinct bit patterns, 300 each
    centres = rng.integers(0, 256, size=(3, 32), dtype=np.uint8)
    descs = []
    for c in centres:
        flips = rng.random((300, 256)) < 0.05
        bits = np.unpackbits(np.repeat(c[None], 300, 0), axis=1) ^ flips
        descs.append(np.packbits(bits.astype(np.uint8), axis=1))
    out = tmp_path / "voc.txt"
    words = op.train_vocabulary(descs, out, k=4, L=3)
    (k, L, scoring, weighting), nodes = _parse_dbow2(out)
    assert (k, L, scoring, weighting) == (4, 3, 0, 0)       # L1 scoring, TF-IDF
    assert not out.read_text().endswith("\n")               # DBoW2 reads lines to the end
    children = {}
    leaves = 0
    for nid, row in enumerate(nodes, start=1):
        assert len(row) == 2 + 32 + 1
        parent, leaf = int(row[0]), int(row[1])
        assert parent < nid and all(0 <= int(b) <= 255 for b in row[2:34])
        children[parent] = children.get(parent, 0) + 1
        weight = float(row[34])
        leaves += leaf
        assert weight >= 0 and (leaf or weight == 0)
    assert leaves == words and 3 <= words <= k ** L
    assert max(children.values()) <= k
    # a word seen in every image weighs log(3/3) = 0; the words here are each in one image
    assert max(float(r[34]) for r in nodes if r[1] == "1") == pytest.approx(np.log(3))


def test_orbslam3_settings_name_the_camera_and_distortion():
    st = op.settings_yaml(500.0, 501.0, 320.0, 240.0, 640, 480, 20.0, [0.1, -0.2, 0.01, 0.02])
    import yaml
    y = yaml.safe_load(st.replace("%YAML:1.0\n", ""))
    assert (y["Camera.fx"], y["Camera.fy"], y["Camera.cx"], y["Camera.cy"]) == \
        (500.0, 501.0, 320.0, 240.0)
    assert (y["Camera.k1"], y["Camera.k2"], y["Camera.p1"], y["Camera.p2"]) == \
        (0.1, -0.2, 0.01, 0.02)
    assert y["Camera.width"] == 640 and y["Camera.fps"] == 20.0
    assert y["ORBextractor.nFeatures"] == op.N_FEATURES
