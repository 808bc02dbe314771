"""keyframe_store: atomic records, crash leftovers, keyframe round trips, mapper snapshots."""
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from splat_slam_ros.io.keyframe_store import KeyframeStore, RecordStore, StoreError
from splat_slam_ros.mapping.mapper import Mapper
from splat_slam_ros.mapping.persistence import keyframe_depth, map_state, restore_mapper
from splat_slam_ros.types import Intrinsics, KeyframeData


def _kf(k, H=24, W=32, rng=None):
    rng = rng or np.random.default_rng(k)
    intr = Intrinsics(30.0, 30.0, 15.5, 11.5, W, H)
    pose = np.eye(4)
    pose[:3, 3] = [0.1 * k, 0.0, 0.0]
    return KeyframeData(kf_id=k, frame_index=3 * k, timestamp=100.0 + k, pose=pose,
                        image=rng.integers(0, 256, (H, W, 3), dtype=np.uint8), intrinsics=intr,
                        disparity=rng.random((H // 8, W // 8)).astype(np.float32) + 0.5,
                        confidence=rng.random((H // 8, W // 8)).astype(np.float32))


def test_records_commit_and_reopen(tmp_path):
    s = RecordStore(tmp_path / "st")
    assert not s.exists
    s.put("a", meta={"n": 1}, x=np.arange(5))
    s.put("a", x=np.arange(6))                        # replaces: the old file is removed
    s.put("b", y=np.ones((2, 2)))
    files = sorted(p.name for p in (tmp_path / "st").iterdir())
    assert files == sorted(["manifest.json", s._records["a"], s._records["b"]])
    s2 = RecordStore(tmp_path / "st")
    assert s2.exists and s2.meta == {"n": 1}
    np.testing.assert_array_equal(s2.get("a")["x"], np.arange(6))
    s2.delete("b")
    assert RecordStore(tmp_path / "st").names() == ["a"]
    with pytest.raises(KeyError):
        s2.get("b")


def test_crash_leftovers_are_ignored_and_cleaned(tmp_path):
    d = tmp_path / "st"
    s = RecordStore(d)
    s.put("a", x=np.arange(3))
    good = s._records["a"]
    # a crash after staging (record written, manifest not switched) and mid-write (tmp file)
    staged = s.stage("a", x=np.arange(99))
    (d / ".r_a.77.npz.123.tmp").write_bytes(b"partial")
    assert (d / staged).is_file()
    s2 = RecordStore(d)
    np.testing.assert_array_equal(s2.get("a")["x"], np.arange(3))
    assert sorted(p.name for p in d.iterdir()) == sorted(["manifest.json", good])
    # new records never reuse the counter of a file seen on disk
    s2.put("a", x=np.arange(4))
    assert s2._records["a"] != staged or not (d / staged).exists()


def test_unreadable_manifest_is_a_clear_error(tmp_path):
    d = tmp_path / "st"
    d.mkdir()
    (d / "manifest.json").write_text("{not json")
    with pytest.raises(StoreError, match="unreadable"):
        RecordStore(d)


def test_killed_writer_leaves_a_consistent_store(tmp_path):
    """SIGKILL a process that commits in a loop: the store always opens, all records load."""
    d = tmp_path / "st"
    code = textwrap.dedent(f"""
        import numpy as np, sys
        from splat_slam_ros.io.keyframe_store import RecordStore
        s = RecordStore({str(d)!r}, fsync=False)
        i = 0
        print("go", flush=True)
        while True:
            s.put(f"k{{i % 7}}", meta={{"i": i}}, x=np.full(20000, i))
            i += 1
    """)
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert p.stdout.readline().strip() == b"go"
    import time
    time.sleep(0.4)
    p.kill()
    p.wait()
    s = RecordStore(d)
    i = s.meta["i"]
    assert i > 0
    for n in s.names():
        x = s.get(n)["x"]
        assert x.shape == (20000,) and (x == x[0]).all() and x[0] <= i
    np.testing.assert_array_equal(s.get(f"k{i % 7}")["x"], np.full(20000, i))


def test_keyframe_round_trip_and_updates(tmp_path):
    s = KeyframeStore(tmp_path / "kf")
    kfs = [_kf(k) for k in range(3)]
    for kf in kfs:
        s.put_keyframe(kf)
    P = np.eye(4)
    P[:3, 3] = [5, 6, 7]
    s.update_keyframe(1, pose=P, disparity=np.full((3, 4), 2.0, np.float32), meta={"seq": 9})
    s.put_proxy_depth(2, np.full((24, 32), 1.5, np.float32), np.ones((24, 32), np.uint8), P, 9)
    s2 = KeyframeStore(tmp_path / "kf")
    assert s2.keyframe_ids() == [0, 1, 2] and s2.meta["seq"] == 9
    back = s2.keyframes()
    np.testing.assert_array_equal(back[0].image, kfs[0].image)
    np.testing.assert_array_equal(back[2].disparity, kfs[2].disparity)
    np.testing.assert_array_equal(back[1].pose, P)
    assert (back[1].disparity == 2.0).all()
    assert back[1].frame_index == 3 and back[1].timestamp == 101.0
    assert back[1].intrinsics.width == 32 and back[1].intrinsics.fx == 30.0
    pd = s2.proxy_depth(2)
    assert pd is not None and int(pd["update_seq"]) == 9 and s2.proxy_depth(0) is None
    # an image-less store (e.g. loop closure keeps only geometry) still round-trips
    s3 = KeyframeStore(tmp_path / "noimg")
    s3.put_keyframe(kfs[0], with_image=False)
    assert s3.keyframe(0).image.shape == (24, 32, 3)


def test_mapper_snapshot_round_trip(tmp_path):
    from splat_slam_ros.config import MappingConfig, SlamConfig
    cfg = SlamConfig()
    cfg.mapping = MappingConfig.fast(iters_first=5, iters_per_keyframe=3)
    H, W = 24, 32
    intr = Intrinsics(30.0, 30.0, 15.5, 11.5, W, H)
    mp = Mapper(cfg, intr)
    rng = np.random.default_rng(0)
    imgs = {}
    for k in range(2):
        img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        imgs[k] = img
        pose = np.eye(4)
        pose[0, 3] = 0.3 * k
        w = None if k == 0 else np.where(np.arange(W) < W // 2, 1.0, 0.3) * np.ones((H, 1))
        mp.add_keyframe(k, img, pose, np.full((H, W), 2.0, np.float32), w, force=True)
    assert mp.keyframes[0].weight is None and mp.keyframes[1].weight is not None
    arrays, meta = map_state(mp)
    st = KeyframeStore(tmp_path / "m")
    st.put("map", meta={"map": meta}, **arrays)
    for k in mp.keyframes:
        st.put(f"d{k}", **keyframe_depth(mp, k))
    st2 = KeyframeStore(tmp_path / "m")
    mp2 = restore_mapper(st2.get("map"), st2.meta["map"], cfg, intr, lambda k: imgs[k],
                         lambda k: st2.get(f"d{k}"))
    for k in mp.keyframes:
        np.testing.assert_array_equal(mp2.keyframes[k].valid.numpy(), mp.keyframes[k].valid.numpy())
        np.testing.assert_array_equal(mp2.keyframes[k].depth.numpy(), mp.keyframes[k].depth.numpy())
    assert mp2.keyframes[0].weight is None      # depth-loss weights (BA-filled holes) kept
    np.testing.assert_allclose(mp2.keyframes[1].weight.numpy(), mp.keyframes[1].weight.numpy(),
                               atol=1e-3)
    assert len(mp2.map) == len(mp.map) and sorted(mp2.keyframes) == sorted(mp.keyframes)
    assert mp2.window.window == mp.window.window and mp2.iteration == mp.iteration
    pose = mp.keyframes[1].pose
    r1, d1 = mp.render(pose)
    r2, d2 = mp2.render(pose)
    np.testing.assert_array_equal(r1, r2)
    np.testing.assert_allclose(d1, d2)
    # the restored mapper keeps working: maps and deforms
    mp2.add_keyframe(2, imgs[0], np.eye(4), np.full((H, W), 2.0, np.float32), force=True)
    assert mp2.apply_update(0, np.eye(4) @ np.diag([1, 1, 1, 1.0])) >= 0
    assert json.dumps(meta)      # metadata is plain JSON
