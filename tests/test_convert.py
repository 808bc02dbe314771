"""Dataset -> rosbag2 (MCAP) -> read back with rosbags AND mcap/mcap_ros2; convert CLI."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from splat_slam_ros.io.bagio import (DEFAULT_TOPICS, INFO_FILE, BagDataset, make_typestore,
                                  register_project_types, write_bag)
from splat_slam_ros.cli.convert import main as convert_main
from splat_slam_ros.io.datasets import DatasetError, open_dataset, stamp_to_ns
from splat_slam_ros.geometry import pose_from_tq
import splat_slam_synth as synth
from splat_slam_ros.io.trajectory_io import read_trajectory
from splat_slam_ros.types import Intrinsics

from test_datasets import (K_SMALL, _write_rgb, _img, make_euroc, make_replica,  # noqa: E402
                           make_scannet, make_tum, make_video, shared)

REPO = Path(__file__).resolve().parents[1]


def read_with_mcap_ros2(bag_dir: Path):
    """Independent decode of every message with mcap + mcap_ros2 (schemas from the file)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    out = {}
    files = sorted(Path(bag_dir).glob("*.mcap"))
    assert len(files) == 1
    with open(files[0], "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in r.iter_decoded_messages():
            out.setdefault(channel.topic, []).append((schema.name, message.log_time, msg))
    return out


def _stamp(msg):
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


def check_round_trip(ds, bag: Path):
    """Frames of ``ds`` == frames read back by both readers (bytes, stamps, poses, depth)."""
    summary = write_bag(ds, bag, progress=False)
    ref = list(ds.iter_frames(keep_mono=True))
    assert summary["frames"] == len(ref) == len(ds)

    for backend in ("rosbags", "mcap"):
        back = list(BagDataset(bag, backend=backend, keep_mono=True))
        assert len(back) == len(ref)
        for a, b in zip(ref, back):
            assert a.index == b.index and a.timestamp == b.timestamp
            assert a.image.tobytes() == b.image.tobytes() and a.image.shape == b.image.shape
            assert b.intrinsics == ds.intrinsics
            if a.gt_pose is None:
                assert b.gt_pose is None
            else:
                np.testing.assert_allclose(b.gt_pose, a.gt_pose, atol=1e-12)
            if a.gt_depth is None:
                assert b.gt_depth is None
            else:
                assert a.gt_depth.tobytes() == b.gt_depth.tobytes()

    # Independent reader: mcap + mcap_ros2, no project code.
    msgs = read_with_mcap_ros2(bag)
    imgs = msgs[DEFAULT_TOPICS["image"]]
    infos = msgs[DEFAULT_TOPICS["camera_info"]]
    assert len(imgs) == len(infos) == len(ref)
    for a, (schema, log_ns, m), (_, _, ci) in zip(ref, imgs, infos):
        assert schema == "sensor_msgs/msg/Image"
        assert m.encoding == ("mono8" if a.image.ndim == 2 else "rgb8")
        assert bytes(m.data) == a.image.tobytes() and m.header.frame_id == "camera"
        assert _stamp(m) == log_ns and log_ns / 10**9 == a.timestamp
        assert list(ci.k) == [ds.intrinsics.fx, 0, ds.intrinsics.cx, 0, ds.intrinsics.fy,
                              ds.intrinsics.cy, 0, 0, 1]
        assert (ci.width, ci.height) == (ds.intrinsics.width, ds.intrinsics.height)
    gts = msgs.get(DEFAULT_TOPICS["gt_pose"], [])
    assert len(gts) == sum(f.gt_pose is not None for f in ref)
    by_stamp = {stamp_to_ns(f.timestamp): f for f in ref}
    for schema, log_ns, m in gts:
        assert schema == "geometry_msgs/msg/PoseStamped" and m.header.frame_id == "world"
        p, q = m.pose.position, m.pose.orientation
        T = pose_from_tq(np.array([p.x, p.y, p.z, q.x, q.y, q.z, q.w])).numpy()
        np.testing.assert_allclose(T, by_stamp[_stamp(m)].gt_pose, atol=1e-12)
    depths = msgs.get(DEFAULT_TOPICS["depth"], [])
    assert len(depths) == sum(f.gt_depth is not None for f in ref)
    for (schema, log_ns, m), a in zip(depths, [f for f in ref if f.gt_depth is not None]):
        assert m.encoding == "32FC1" and m.step == 4 * m.width
        d = np.frombuffer(bytes(m.data), "<f4").reshape(m.height, m.width)
        np.testing.assert_array_equal(d, a.gt_depth)
    return msgs, summary


# ----------------------------------------------------------------- round trips
def test_round_trip_tum(tmp_path):
    root, _, _ = make_tum(tmp_path / "seq", n=5)
    ds = open_dataset(root)
    msgs, summary = check_round_trip(ds, tmp_path / "bag")
    assert set(summary["topics"]) == set(DEFAULT_TOPICS.values())
    assert summary["duration_s"] == pytest.approx(4 / 30, abs=1e-5)
    # metadata: custom_data in metadata.yaml and the info file
    meta = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap"
    assert info["custom_data"]["splat_slam.format"] == "tum"
    assert info["custom_data"]["splat_slam.name"] == "seq"
    side = yaml.safe_load((tmp_path / "bag" / INFO_FILE).read_text())
    assert side["frames"] == 5 and side["has_gt_depth"] and side["depth_scale"] == 5000.0
    b = open_dataset(tmp_path / "bag")
    assert b.format == "bag" and b.name == "seq" and b.source_format == "tum"
    assert b.has_gt_pose and b.has_gt_depth
    np.testing.assert_allclose(b.gt_trajectory()[1], ds.gt_trajectory()[1], atol=1e-12)
    # a bag's frames without depth (a run tracks without it), and by timestamp with it
    assert all(f.gt_depth is None for f in b.iter_frames(depth=False))
    ts = [f.timestamp for f in ds]
    got = list(b.frames_at_stamps([ts[3], ts[1]]))
    assert [f.index for f in got] == [1, 3] and all(f.gt_depth is not None for f in got)
    np.testing.assert_allclose(got[1].gt_depth, next(ds.frames_at([3], depth=True)).gt_depth,
                               atol=1e-3)


def test_round_trip_euroc_mono8_and_distortion(tmp_path):
    root, _, _ = make_euroc(tmp_path / "V1")
    ds = open_dataset(root)
    msgs, _ = check_round_trip(ds, tmp_path / "bag")
    ci = msgs[DEFAULT_TOPICS["camera_info"]][0][2]
    assert ci.distortion_model == "plumb_bob"
    assert list(ci.d) == pytest.approx([-0.28, 0.07, 0.0002, 0.00002, 0.0])
    assert DEFAULT_TOPICS["depth"] not in msgs
    rgb = next(iter(BagDataset(tmp_path / "bag")))        # default: mono expanded to RGB
    assert rgb.image.shape == (24, 32, 3)


def test_round_trip_replica_scannet_video(tmp_path):
    check_round_trip(open_dataset(make_replica(tmp_path / "R" / "room0")), tmp_path / "b1")
    check_round_trip(open_dataset(make_scannet(tmp_path / "scene")), tmp_path / "b2")
    make_video(tmp_path / "v.avi", n=4)
    K_SMALL.to_yaml(tmp_path / "k.yaml")
    check_round_trip(open_dataset(tmp_path / "v.avi", intrinsics=tmp_path / "k.yaml"),
                     tmp_path / "b3")


def test_round_trip_shared_real_data(shared_data, tmp_path):
    k = tmp_path / "icl.yaml"
    Intrinsics(481.2, -480.0, 319.5, 239.5, 640, 480).to_yaml(k, depth_scale=5000)
    ds = open_dataset(shared(shared_data, "icl_nuim_living_room_5"), intrinsics=k,
                      max_frames=2)
    check_round_trip(ds, tmp_path / "icl")
    ds = open_dataset(shared(shared_data, "euroc_v1_01_first95"), max_frames=3, stride=10)
    msgs, _ = check_round_trip(ds, tmp_path / "euroc")
    assert msgs[DEFAULT_TOPICS["image"]][0][2].encoding == "mono8"


def test_bag_stride_max_frames_and_bare_mcap(tmp_path):
    root, stamps, _ = make_tum(tmp_path / "seq", n=6)
    write_bag(open_dataset(root), tmp_path / "bag", progress=False, compress=True)
    b = BagDataset(tmp_path / "bag", stride=2, max_frames=2)
    fr = list(b)
    assert len(b) == 2 and [f.timestamp for f in fr] == pytest.approx(stamps[0:4:2], abs=1e-6)
    assert len(b.gt_trajectory()[0]) == 2
    # a bare .mcap file (metadata.yaml gone) is read with mcap_ros2
    mcap = next((tmp_path / "bag").glob("*.mcap"))
    lone = tmp_path / "lone.mcap"
    lone.write_bytes(mcap.read_bytes())
    b2 = open_dataset(lone)
    assert b2.backend == "mcap" and len(b2) == 6
    assert [f.timestamp for f in b2] == pytest.approx(stamps, abs=1e-6)


def test_write_failure_removes_partial_bag(tmp_path):
    root, stamps, _ = make_tum(tmp_path / "seq", n=3)
    (root / "rgb" / f"{stamps[2]:.6f}.png").write_bytes(b"garbage")
    ds = open_dataset(root)
    with pytest.raises(DatasetError, match=r"cannot read image"):
        write_bag(ds, tmp_path / "bag", progress=False)
    assert not (tmp_path / "bag").exists()


def test_bag_errors(tmp_path):
    with pytest.raises(DatasetError, match=r"bag not found"):
        BagDataset(tmp_path / "nope")
    (tmp_path / "d").mkdir()
    with pytest.raises(DatasetError, match=r"not a rosbag2 folder \(no metadata.yaml\)"):
        BagDataset(tmp_path / "d")
    root, _, _ = make_tum(tmp_path / "seq", n=2)
    write_bag(open_dataset(root), tmp_path / "bag", progress=False)
    with pytest.raises(DatasetError, match=r"bag has no image topic '/cam/rgb'"):
        BagDataset(tmp_path / "bag", topics={"image": "/cam/rgb"})


# ---------------------------------------------------------------- typestore
def test_register_project_types(tmp_path):
    ts = make_typestore(project_types=False)
    assert register_project_types(ts, tmp_path / "missing") == []
    names = register_project_types(ts)
    assert "splat_slam_msgs/msg/Keyframe" in names
    assert "splat_slam_msgs/msg/Keyframe" in ts.types


# --------------------------------------------------------------------- CLI
def test_cli_convert_overwrite_and_errors(tmp_path, capsys):
    root, _, _ = make_tum(tmp_path / "seq", n=3)
    out = tmp_path / "bags" / "seq"
    assert convert_main([str(root), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "3 frames" in text and "/camera/image_raw: 3 messages" in text
    assert "/ground_truth/pose: 3 messages" in text and ("MiB" in text or "KiB" in text)
    assert convert_main([str(root), "--out", str(out), "--quiet"]) == 2
    assert "error: output" in capsys.readouterr().err
    assert convert_main([str(root), "--out", str(out), "--quiet", "--overwrite",
                         "--max-frames", "2"]) == 0
    assert len(BagDataset(out)) == 2
    assert convert_main([str(out), "--info"]) == 0
    text = capsys.readouterr().out
    assert "bag 'seq', 2 frames 32x24" in text and "converted from: tum" in text
    assert "/camera/depth: sensor_msgs/msg/Image, 2 messages" in text
    # --overwrite never deletes a folder that is not a bag
    other = tmp_path / "precious"
    other.mkdir()
    (other / "keep.txt").write_text("x")
    assert convert_main([str(root), "--out", str(other), "--overwrite", "--quiet"]) == 2
    assert "not a rosbag2 folder; not deleting it" in capsys.readouterr().err
    assert (other / "keep.txt").exists()
    # user mistakes: one 'error:' line, exit 2, no traceback
    assert convert_main([str(tmp_path / "missing"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: dataset path not found") and "Traceback" not in err
    img_dir = tmp_path / "imgs"
    _write_rgb(img_dir / "a.png", _img(0))
    assert convert_main([str(img_dir), "--out", str(tmp_path / "y")]) == 2
    assert "no intrinsics" in capsys.readouterr().err
    K_SMALL.to_yaml(tmp_path / "k.yaml")
    assert convert_main([str(img_dir), "--out", str(tmp_path / "y"), "--intrinsics",
                         str(tmp_path / "k.yaml"), "--fps", "15", "--quiet"]) == 0


def test_synthetic_sequence_converts(tmp_path, capsys):
    """splat-slam-synth output (TUM layout + intrinsics.yaml) -> convert CLI -> bag."""
    seq = synth.generate_sequence("builtin", frames=3, size="64x48", out=tmp_path / "syn",
                                  progress=False)
    ds = open_dataset(seq)
    assert ds.format == "tum" and len(ds) == 3 and ds.has_gt_pose and ds.has_gt_depth
    assert (ds.intrinsics.width, ds.intrinsics.height) == (64, 48)
    assert convert_main([str(seq), "--out", str(tmp_path / "bag"), "--quiet"]) == 0
    capsys.readouterr()
    back = list(BagDataset(tmp_path / "bag"))
    ts, P = read_trajectory(Path(seq) / "groundtruth.txt")
    assert len(back) == 3
    for f, t, T, ref in zip(back, ts, P, ds):
        assert f.timestamp == pytest.approx(t, abs=1e-6)
        np.testing.assert_allclose(f.gt_pose, T, atol=1e-9)   # GT at the image stamps
        assert f.image.tobytes() == ref.image.tobytes()
        assert f.gt_depth.tobytes() == ref.gt_depth.tobytes() and f.gt_depth.max() > 0
