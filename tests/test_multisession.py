"""Maps across sessions: a run saves OUT/session/, a later run (--load-map OUT --localize)
relocalises in it and tracks in its frame without changing the map, or (--load-map OUT)
extends the map; --start-frame."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from splat_slam_ros.evaluation.trajectory import umeyama_alignment
from splat_slam_ros.io import session as ss
from splat_slam_ros.io.trajectory_io import read_trajectory
from splat_slam_ros.mapping.persistence import mapper_arrays, restore_map_state

PY = sys.executable
CFG = """
tracking: {warmup: 4, motion_filter_thresh: 2.0, keyframe_thresh: 2.0, ba_downsample: 4}
mapping: {iters_first: 30, iters_per_keyframe: 5, final_refine_iters: 10,
          random_views_per_iter: 1, window_views_per_iter: 2}
"""


def _render(d: Path, frames: int, size=(160, 120), **kw) -> Path:
    from splat_slam_synth import generate_sequence
    generate_sequence("builtin", frames, size, d, overwrite=True, progress=False,
                      realism="clean", fps=10, **kw)
    return d


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "splat_slam_ros.cli.run", *map(str, args), "--no-progress"],
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    root = tmp_path_factory.mktemp("multisession")
    seq = _render(root / "seq", 50)
    cfg = root / "cfg.yaml"
    cfg.write_text(CFG)
    s1, s2 = root / "s1", root / "s2"
    r1 = _run(seq, "--out", s1, "--config", cfg, "--max-frames", 40)
    assert r1.returncode == 0, r1.stderr[-2000:]
    r2 = _run(seq, "--out", s2, "--config", cfg, "--start-frame", 20, "--load-map", s1,
              "--localize")
    return {"root": root, "seq": seq, "cfg": cfg, "s1": s1, "s2": s2, "r2": r2}


def _keyframes(n=3, h=6, w=8) -> ss.SessionKeyframes:
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(4)[None], n, 0)
    poses[:, :3, 3] = rng.normal(size=(n, 3))
    imgs = rng.integers(0, 255, (n, 4 * h, 4 * w, 3), dtype=np.uint8)
    return ss.SessionKeyframes(
        kf_ids=np.arange(n, dtype=np.int64), frame_indices=np.arange(n, dtype=np.int64) * 3,
        timestamps=np.arange(n) * 0.3, poses=poses,
        disparities=rng.random((n, h, w), dtype=np.float32), images=imgs,
        descriptors=np.stack([ss.descriptor(i) for i in imgs]))


def _camera():
    from splat_slam_ros.types import Intrinsics
    return Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)


def test_session_round_trip_and_checksums(tmp_path):
    from splat_slam_ros.config import load_config
    from splat_slam_ros.mapping.mapper import Mapper
    kfs = _keyframes()
    # the graph writes the two parts from two processes, in either order: the map state first
    mp = Mapper(load_config(None), _camera())
    mp.save_ply(tmp_path / "map.ply")
    ss.write_map_state(tmp_path, *mapper_arrays(mp), mp.K)
    with pytest.raises(ss.SessionError, match="corrupt"):     # half a session: not loadable
        ss.load_session(tmp_path)
    ss.write_session_keyframes(tmp_path, kfs, _camera(), (32, 24), (8, 6), {"a": 1}, "0.1.0")
    s = ss.load_session(tmp_path)
    for k in ss.ARRAYS:
        np.testing.assert_array_equal(getattr(s.keyframes, k), getattr(kfs, k))
    m = s.manifest
    assert m["version"] == ss.VERSION and m["keyframes"] == 3 and m["config"] == {"a": 1}
    assert m["files"]["keyframes.npz"] == ss.sha256(tmp_path / "session" / "keyframes.npz")
    assert m["files"]["map_state.npz"] == ss.sha256(tmp_path / "session" / "map_state.npz")
    assert s.map_path == (tmp_path / "map.ply").resolve() and m["map_note"] is None
    assert m["camera"]["fx"] == 30.0 and m["ba_size"] == [8, 6]
    assert ss.map_camera(s).to_dict() == _camera().to_dict()
    # a map changed after the session was saved no longer matches its checksum
    (tmp_path / "map.ply").write_bytes(b"ply\nanother map\n")
    with pytest.raises(ss.SessionError, match=r"map\.ply does not match its sha256"):
        ss.load_session(tmp_path)
    # the descriptor: unit norm, the same image matches itself best
    d = kfs.descriptors
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert list(ss.descriptor_ranking(d, d[1]))[0] == 1


def test_npz_entries_are_the_npy_bytes_and_the_file_is_the_same_every_time(tmp_path):
    """A session's npz: each entry holds what np.save writes (0-d, empty, strided, bool and
    big-endian arrays included), np.load reads it, and the same arrays give the same bytes."""
    import io
    import zipfile
    rng = np.random.default_rng(3)
    arrays = {"scalar": np.asarray(640), "empty": np.zeros((0, 192), np.float32),
              "strided": rng.random((6, 8))[:, ::2], "mask": rng.random((4, 5)) > 0.5,
              "be": np.arange(5, dtype=">i4"), "images": rng.integers(0, 255, (3, 24, 32, 3),
                                                                  dtype=np.uint8)}
    ss._write_npz(tmp_path / "a.npz", arrays)
    ss._write_npz(tmp_path / "b.npz", arrays)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with zipfile.ZipFile(tmp_path / "a.npz") as z, np.load(tmp_path / "a.npz") as f:
        for name, a in arrays.items():
            ref = io.BytesIO()
            np.save(ref, a, allow_pickle=False)
            assert z.read(f"{name}.npy") == ref.getvalue()
            assert f[name].shape == a.shape and f[name].dtype == a.dtype
            np.testing.assert_array_equal(f[name], a)


def test_npz_streamed_in_chunks_is_the_one_write_file(tmp_path):
    """An array of several NPZ_CHUNK pieces is streamed into its entry; the file has the bytes
    zipfile writes for the whole .npy in one writestr at the same level (same checksum)."""
    import io
    import zipfile
    rng = np.random.default_rng(5)
    arrays = {"images": rng.integers(0, 255, (3 * ss.NPZ_CHUNK // 900 + 1, 20, 15, 3),
                                     dtype=np.uint8),
              "disparities": rng.random((7, 30, 40)).astype(np.float32)}
    assert arrays["images"].nbytes > 2 * ss.NPZ_CHUNK
    ss._write_npz(tmp_path / "streamed.npz", arrays)
    with zipfile.ZipFile(tmp_path / "ref.npz", "w", zipfile.ZIP_DEFLATED) as z:
        for name, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, a, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, buf.getvalue(), compresslevel=ss.NPZ_LEVEL)
    assert (tmp_path / "streamed.npz").read_bytes() == (tmp_path / "ref.npz").read_bytes()


def test_full_run_saves_its_keyframes(work):
    s = ss.load_session(work["s1"])
    kts, kposes = read_trajectory(work["s1"] / "trajectory_keyframes.txt")
    k = s.keyframes
    assert len(k) == len(kts) >= 5
    np.testing.assert_allclose(k.timestamps, kts, atol=1e-4)
    np.testing.assert_allclose(k.poses[:, :3, 3], kposes[:, :3, 3], atol=1e-5)
    assert k.images.shape[1:] == (120, 160, 3) and k.disparities.shape[1:] == (30, 40)
    assert k.frame_indices.max() <= 39
    assert s.map_path is not None and s.manifest["map"]["bytes"] > 1000
    # the loop-closure graph: edges between the session's keyframes (each joined to the graph)
    g, ids = ss.loop_graph(s), set(k.kf_ids.tolist())
    assert g is not None and len(g["edges"]) >= len(k) - 1
    assert all(i in ids and j in ids for i, j, _kind in g["edges"])
    assert {i for e in g["edges"] for i in e[:2]} == ids - {m[0] for m in g["merged"]}


def _gt(seq: Path):
    rows = [ln.split() for ln in (seq / "groundtruth.txt").read_text().splitlines()
            if ln and not ln.startswith("#")]
    return {round(float(r[0]), 3): np.array(r[1:4], float) for r in rows}


def test_localize_tracks_in_the_first_sessions_frame(work):
    r2, s1, s2 = work["r2"], work["s1"], work["s2"]
    assert r2.returncode == 0, r2.stderr[-2000:]
    m = json.loads((s2 / "metrics.json").read_text())
    assert m["localize"] is True and m["frames"] == 30
    assert 20 <= m["relocalised_frame"] <= 23, m
    assert m["frames_posed"] + m["frames_lost"] == 30 and m["frames_posed"] >= 25
    assert f"relocalised at frame {m['relocalised_frame']} against keyframe " \
        f"{m['relocalised_keyframe']}\n" in r2.stdout
    assert (s2 / "map.ply").read_bytes() == (s1 / "map.ply").read_bytes()
    # ONE Sim(3) for both sessions' trajectories together: the same frame
    gt = _gt(work["seq"])
    est, ref = [], []
    for run in (s1, s2):
        ts, P = read_trajectory(run / "trajectory_full.txt")
        for t, T in zip(ts, P):
            est.append(T[:3, 3])
            ref.append(gt[round(float(t), 3)])
    est, ref = np.array(est), np.array(ref)
    s, R, t = umeyama_alignment(est, ref, with_scale=True)
    err = np.linalg.norm((s * (R @ est.T)).T + t - ref, axis=1)
    rmse_cm = 100 * float(np.sqrt(np.mean(err ** 2)))
    assert rmse_cm < 2.0, rmse_cm
    # frames both sessions posed: the same poses, without any alignment
    ts1, P1 = read_trajectory(s1 / "trajectory_full.txt")
    ts2, P2 = read_trajectory(s2 / "trajectory_full.txt")
    both = {round(float(t), 3): T for t, T in zip(ts1, P1)}
    common = [(both[round(float(t), 3)], T) for t, T in zip(ts2, P2) if round(float(t), 3) in both]
    assert len(common) >= 15
    span = np.ptp(P1[:, :3, 3], axis=0).max()
    assert max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in common) < 0.05 * span


def _main(capsys, *args):
    from splat_slam_ros.cli.run import main
    code = main([*map(str, args), "--no-progress"])
    return code, capsys.readouterr().err.strip().splitlines()


def _copy_run(work, name):
    dst = work["root"] / name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(work["s1"], dst)
    return dst


def test_bad_sessions_exit_2_before_any_frame(work, capsys, tmp_path):
    seq, out = work["seq"], tmp_path / "out"
    bad = _copy_run(work, "corrupt")
    kp = bad / "session" / "keyframes.npz"
    kp.write_bytes(kp.read_bytes()[:-100] + b"x" * 100)
    code, err = _main(capsys, seq, "--out", out, "--load-map", bad, "--localize")
    assert code == 2 and len(err) == 1 and "keyframes.npz does not match its sha256" in err[0]
    # a corrupt file whose checksum was updated too: unreadable
    mf = bad / "session" / "manifest.json"
    m = json.loads(mf.read_text())
    kp.write_bytes(b"not a zip file")
    m["files"]["keyframes.npz"] = ss.sha256(kp)
    mf.write_text(json.dumps(m))
    code, err = _main(capsys, seq, "--out", out, "--load-map", bad, "--localize")
    assert code == 2 and "keyframes.npz is unreadable" in err[0], err
    newer = _copy_run(work, "newer")
    mf = newer / "session" / "manifest.json"
    m = json.loads(mf.read_text())
    m["version"] = ss.VERSION + 1
    mf.write_text(json.dumps(m))
    code, err = _main(capsys, seq, "--out", out, "--load-map", newer, "--localize")
    assert code == 2 and f"format version {ss.VERSION + 1}" in err[0] and \
        f"reads version {ss.VERSION} only" in err[0], err
    code, err = _main(capsys, seq, "--out", out, "--load-map", tmp_path, "--localize")
    assert code == 2 and err == [f"error: no saved session in {tmp_path} "
                                 f"({tmp_path / 'session' / 'manifest.json'} not found; runs "
                                 f"of splat-slam-run write one)"]
    small = _render(tmp_path / "small", 3, size=(128, 96))
    code, err = _main(capsys, small, "--out", out, "--config", work["cfg"], "--load-map",
                      work["s1"], "--localize")
    assert code == 2 and len(err) == 1 and "another camera" in err[0] and \
        "width 160 vs 128" in err[0] and "fx 131.25 vs 105" in err[0], err
    assert not (out / "metrics.json").exists()


def test_option_mistakes_exit_2(work, capsys, tmp_path):
    seq, out = work["seq"], tmp_path / "out"
    for args, msg in (
            (["--localize"], "--localize needs --load-map"),
            (["--load-map", work["s1"], "--tracking-only"], "--tracking-only cannot extend"),
            (["--start-frame", -1], "--start-frame must be >= 0"),
            (["--load-map", out, "--localize"], "--out must be another folder than --load-map"),
            (["--start-frame", 50], "--start-frame 50 is outside the input's frames "
                                    "(0 <= N < 50)")):
        code, err = _main(capsys, seq, "--out", out, *args)
        assert code == 2 and len(err) == 1 and msg in err[0], (args, err)


def test_start_frame_skips_the_first_frames(work, tmp_path):
    from splat_slam_ros.io.datasets import FromFrame, open_dataset
    ds = FromFrame(open_dataset(work["seq"]), 45)
    frames = list(ds)
    assert len(ds) == 5 and [f.index for f in frames] == [45, 46, 47, 48, 49]
    ts, _ = ds.gt_trajectory()
    assert len(ts) == 5 and abs(ts[0] - frames[0].timestamp) < 1e-6


@pytest.fixture(scope="module")
def other(tmp_path_factory):
    """The same camera path through another room (another seed)."""
    return _render(tmp_path_factory.mktemp("other") / "seq", 12, seed=7)


def test_a_lost_frame_relocalises_again(work, other):
    from splat_slam_ros.config import load_config
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_ros.tracking.relocalise import Localizer
    ds = open_dataset(work["seq"])
    loc = Localizer(load_config(str(work["cfg"])), ds.intrinsics, ss.load_session(work["s1"]))
    strange = next(iter(open_dataset(other)))
    poses = {}
    for f in ds:
        if 20 <= f.index < 30:
            if f.index == 25:       # a view of another room: lost, then relocalised again
                f = type(f)(f.index, f.timestamp, strange.image, f.intrinsics)
            poses[f.index] = loc.track(f)
    assert poses[25] is None and loc.n_lost == 1 and not any(
        poses[i] is None for i in poses if i != 25)
    assert loc.relocalised_frame == 20 and loc.n_relocalisations == 2
    ts, P = read_trajectory(work["s1"] / "trajectory_full.txt")
    first = {round(float(t), 3): T for t, T in zip(ts, P)}
    span = np.ptp(P[:, :3, 3], axis=0).max()
    for i, f in enumerate(ds):
        if i in (24, 26):           # either side of the lost frame: the first run's poses
            T = first[round(float(f.timestamp), 3)]
            assert np.linalg.norm(poses[i][:3, 3] - T[:3, 3]) < 0.05 * span


def test_another_room_never_relocalises(work, other, tmp_path):
    out = tmp_path / "out"
    r = _run(other, "--out", out, "--config", work["cfg"], "--load-map", work["s1"],
             "--localize")
    assert r.returncode == 3, r.stderr[-2000:]
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith("error: never relocalised in the loaded map: none of the 12 "
                                "frames"), lines
    m = json.loads((out / "metrics.json").read_text())
    assert m["relocalised_frame"] is None and m["frames_posed"] == 0 and m["frames_lost"] == 12
    assert not (out / "trajectory_full.txt").exists()


def test_the_same_keyframes_give_the_same_bytes(tmp_path):
    kfs = _keyframes()
    for d in ("a", "b"):
        ss.write_session(tmp_path / d, kfs, _camera(), (32, 24), (8, 6), {}, "0.1.0")
    a, b = (ss.load_session(tmp_path / d).manifest for d in ("a", "b"))
    assert a["files"] == b["files"] and a["map"] is None and "no map" in a["map_note"]
    import zipfile
    with zipfile.ZipFile(tmp_path / "a" / "session" / "keyframes.npz") as z:
        assert {i.date_time for i in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_tracking_only_session_has_no_map(work, tmp_path):
    t1, t2 = tmp_path / "t1", tmp_path / "t2"
    r = _run(work["seq"], "--out", t1, "--config", work["cfg"], "--tracking-only",
             "--max-frames", 30)
    assert r.returncode == 0, r.stderr[-2000:]
    s = ss.load_session(t1)
    assert s.map_path is None and s.manifest["map"] is None
    assert "tracking-only" in s.manifest["map_note"] and len(s.keyframes) >= 4
    r = _run(work["seq"], "--out", t2, "--config", work["cfg"], "--start-frame", 25,
             "--max-frames", 10, "--load-map", t1, "--localize")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((t2 / "metrics.json").read_text())
    assert m["relocalised_frame"] == 25 and m["frames_posed"] == 10 and m["map"] is None
    assert not (t2 / "map.ply").exists()


def test_a_run_without_keyframes_leaves_no_stale_session(work, tmp_path, capsys):
    out = tmp_path / "again"
    shutil.copytree(work["s1"], out)
    assert (out / "session" / "manifest.json").is_file()
    code, err = _main(capsys, work["seq"], "--out", out, "--config", work["cfg"], "--tracking-only",
                      "--max-frames", 2)
    assert code == 3 and "never initialised" in err[-1]
    with pytest.raises(ss.SessionError, match="no saved session"):
        ss.load_session(out)


# ---------------------------------------------------------------------------- extend
def _metrics(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


@pytest.fixture(scope="module")
def ext(work):
    """A map of the first 20 frames, extended over frames 20-49 (a new part of the room) and
    over frames 0-19 again (a revisit)."""
    root, seq, cfg = work["root"], work["seq"], work["cfg"]
    runs = {n: root / n for n in ("a", "grow", "again")}
    r = _run(seq, "--out", runs["a"], "--config", cfg, "--max-frames", 20)
    assert r.returncode == 0, r.stderr[-2000:]
    for name, args in (("grow", ["--start-frame", 20]), ("again", ["--max-frames", 20])):
        r = _run(seq, "--out", runs[name], "--config", cfg, "--load-map", runs["a"], *args)
        assert r.returncode == 0, r.stderr[-2000:]
        runs[name + "_stdout"] = r.stdout
    return runs


def test_extend_grows_the_loaded_map_in_its_frame(work, ext):
    a, grow = ext["a"], ext["grow"]
    ma, m = _metrics(a), _metrics(grow)
    x = m["extend"]
    assert m["mode"] == "extend" and x["session"] == str(a)
    assert x["loaded"]["keyframes"] == ma["keyframes"] and \
        x["loaded"]["gaussians"] == ma["map"]["gaussians"]
    assert x["relocalised_frame"] == 20 and x["frames_before_relocalised"] == 0
    assert x["new_keyframes"] >= 3 and m["keyframes"] == ma["keyframes"] + x["new_keyframes"]
    # the loaded keyframes by cause, not in the rate (frames 20-49 at 10 Hz: 2.9 s)
    assert m["keyframe_causes"]["loaded"] == ma["keyframes"]
    assert m["keyframes_per_s"] == pytest.approx(x["new_keyframes"] / 2.9, rel=0.02)
    assert x["gaussians"] == m["map"]["gaussians"] > 1.2 * x["loaded"]["gaussians"]
    assert x["mapped_keyframes"] > x["loaded"]["mapped_keyframes"]
    assert f"keyframes {ma['keyframes']} loaded + {x['new_keyframes']} new" in ext["grow_stdout"]
    # the loaded keyframes stay where they were (held fixed as the gauge): the same poses
    ka, Pa = read_trajectory(a / "trajectory_keyframes.txt")
    kg, Pg = read_trajectory(grow / "trajectory_keyframes.txt")
    np.testing.assert_allclose(kg[:len(ka)], ka, atol=1e-4)
    np.testing.assert_allclose(Pg[:len(ka)], Pa, atol=1e-5)
    # ONE Sim(3) for both runs' trajectories: the second run is in the first one's frame
    gt = _gt(work["seq"])
    est, ref = [], []
    for run in (a, grow):
        ts, P = read_trajectory(run / "trajectory_full.txt")
        est += [T[:3, 3] for T in P]
        ref += [gt[round(float(t), 3)] for t in ts]
    assert len(est) == 50
    est, ref = np.array(est), np.array(ref)
    s, R, t = umeyama_alignment(est, ref, with_scale=True)
    rmse_cm = 100 * float(np.sqrt(np.mean(np.sum(((s * (R @ est.T)).T + t - ref) ** 2, 1))))
    assert rmse_cm < 2.0, rmse_cm
    # the extended map is a session again, with every keyframe and the mapper's state
    s2 = ss.load_session(grow)
    assert len(s2.keyframes) == m["keyframes"] and s2.manifest["map_state"] is not None
    arrays, _meta, _cam = ss.map_state(s2)
    assert len(arrays["means"]) == x["gaussians"]


def test_extend_a_revisited_view_adds_no_gaussians(ext):
    x = _metrics(ext["again"])["extend"]
    assert x["relocalised_frame"] == 0 and x["new_keyframes"] >= 2
    assert x["gaussians"] <= 1.02 * x["loaded"]["gaussians"], x
    assert x["mapped_keyframes"] <= x["loaded"]["mapped_keyframes"] + 1, x
    # the same views again: loops from the new keyframes to the loaded ones (held fixed)
    assert x["loop_edges_to_loaded"] >= 1, x
    # the extended session keeps the loaded graph and adds the new edges and loops
    first, again = (ss.load_session(ext[n]) for n in ("a", "again"))
    g1, g2 = ss.loop_graph(first), ss.loop_graph(again)
    assert {tuple(e) for e in g1["edges"]} <= {tuple(e) for e in g2["edges"]}
    pairs = {tuple(p) for p in g2["loop_pairs"]}
    assert {tuple(p) for p in g1["loop_pairs"]} <= pairs
    loaded = set(first.keyframes.kf_ids.tolist())
    assert sum(len(set(p) & loaded) == 1 for p in pairs) == x["loop_edges_to_loaded"]


def test_map_state_round_trip(ext):
    from splat_slam_ros.config import load_config
    s = ss.load_session(ext["a"])
    arrays, meta, cam = ss.map_state(s)
    mp = restore_map_state(arrays, meta, load_config(None), cam)
    again, meta2 = mapper_arrays(mp)
    # restored settled: its Gaussians are a finished map's (opacity pruning spares them)
    assert meta2.pop("settled_uid") == meta["next_uid"] and meta.pop("settled_uid") == 0
    assert sorted(again) == sorted(arrays) and meta2 == meta
    for k, v in arrays.items():
        np.testing.assert_array_equal(again[k], v, err_msg=k)
    assert len(mp.keyframes) == len(arrays["kf_ids"]) > 2 and len(mp.map) > 100


def test_extend_rejects_what_it_cannot_extend(work, ext, other, capsys, tmp_path):
    seq, out = work["seq"], tmp_path / "out"
    t1 = tmp_path / "t1"
    r = _run(seq, "--out", t1, "--config", work["cfg"], "--tracking-only", "--max-frames", 20)
    assert r.returncode == 0, r.stderr[-2000:]
    code, err = _main(capsys, seq, "--out", out, "--config", work["cfg"], "--load-map", t1)
    assert code == 2 and "has no map to extend (a tracking-only run)" in err[-1], err
    bad = tmp_path / "bad"
    shutil.copytree(ext["a"], bad)
    st = bad / "session" / "map_state.npz"
    st.write_bytes(st.read_bytes()[:-50] + b"x" * 50)
    code, err = _main(capsys, seq, "--out", out, "--config", work["cfg"], "--load-map", bad)
    assert code == 2 and "map_state.npz does not match its sha256" in err[-1], err
    assert not out.exists()
    r = _run(other, "--out", out, "--config", work["cfg"], "--load-map", ext["a"])
    assert r.returncode == 3, r.stderr[-2000:]
    assert "never relocalised in the loaded map: none of the 12 frames" in r.stderr
    m = _metrics(out)
    assert m["extend"]["relocalised_frame"] is None and m["extend"]["frames_before_relocalised"] == 12
    assert not (out / "map.ply").exists() and not (out / "trajectory_full.txt").exists()


def test_frames_without_a_keyframe_of_their_input_are_not_placed():
    """Extend runs: a frame tracked against a loaded keyframe (no time in this input) is
    placed from it; a lost one, with no keyframe of this input to interpolate, is not."""
    import torch
    from splat_slam_ros.tracking.trajectory_filler import FrameRecord, fill_trajectory
    h, w = 6, 8
    T = torch.eye(4, dtype=torch.float64)
    T[0, 3] = 0.5
    rel = np.eye(4)
    rel[1, 3] = 0.1
    zero = torch.zeros(h, w, 2, dtype=torch.float16)
    recs = [FrameRecord(0, 1.0, lost=True),
            FrameRecord(1, 1.1, ref_kf=7, rel_pose=rel, flow=zero, weight=zero)]
    ts, P = fill_trajectory(recs, {7: T}, {7: torch.ones(h, w)},
                            torch.tensor([8.0, 8.0, 4.0, 3.0]), iters=0)
    assert list(ts) == [1.1]
    np.testing.assert_allclose(P[0][:3, 3], [0.5, 0.1, 0.0])


def test_extend_relocalises_again_after_a_loss_mid_run(work, other):
    """A long loss mid-run (more than tracking.reinit_after frames of another room): the
    extend tracker relocalises in the loaded map again, no new frame of reference."""
    from splat_slam_ros.config import load_config
    from splat_slam_ros.io.datasets import open_dataset
    from splat_slam_ros.tracking.relocalise import ExtendTracker
    ds = open_dataset(work["seq"])
    cfg = load_config(str(work["cfg"]))
    trk = ExtendTracker(cfg, ds.intrinsics, ss.load_session(work["s1"]))
    # loaded keyframes (same stamps as these frames) are never counted in the rate bound
    assert trk.loaded_ids and all(trk.kfs[k].cause == "loaded" for k in trk.loaded_ids)
    strange = next(iter(open_dataset(other))).image
    steps = {}
    for f in ds:
        if 20 <= f.index < 40:
            if 25 <= f.index < 25 + cfg.tracking.reinit_after + 2:
                f = type(f)(f.index, f.timestamp, strange, f.intrinsics)
            steps[f.index] = trk.track(f)
    assert trk.relocalised_frame == 20 and trk.n_relocalisations == 2, trk.n_relocalisations
    assert not steps[39].lost and trk.initialized
    ts, P = read_trajectory(work["s1"] / "trajectory_full.txt")
    first = {round(float(t), 3): T for t, T in zip(ts, P)}
    span = np.ptp(P[:, :3, 3], axis=0).max()
    T = first[round(float(steps[39].timestamp), 3)]
    assert np.linalg.norm(steps[39].pose[:3, 3] - T[:3, 3]) < 0.05 * span
