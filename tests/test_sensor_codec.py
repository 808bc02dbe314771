"""The one Image / CameraInfo codec (splat_slam_ros.io.sensor_codec) on rosbags and rclpy
messages alike, and the one bag reader (io.bag_reader.BagFile) used by BagDataset and the
bag player."""
import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image as RclpyImage

from splat_slam_nodes import convert as C
from splat_slam_nodes.tools.bag_player import BagReader, PlayerError
from splat_slam_ros.io import bagio
from splat_slam_ros.io.bag_reader import BagFile
from splat_slam_ros.io.dataset_base import DatasetError
from splat_slam_ros.io.sensor_codec import (ConversionError, UnsupportedEncoding,
                                            camera_info_to_intrinsics, decode_depth, decode_image,
                                            decode_rgb, encode_image)
from splat_slam_ros.types import Intrinsics

TS = bagio.make_typestore(project_types=False)
K = Intrinsics(50.0, 52.0, 15.5, 11.5, 32, 24, "plumb_bob", [0.1, -0.02, 0.0, 0.0, 0.0])


def rosbags_image(a, encoding, big=False, pad=0):
    """A rosbags-typestore Image (as BagDataset decodes them) built by hand."""
    a = np.ascontiguousarray(a)
    if big:
        a = a.astype(a.dtype.newbyteorder(">"))
    h, w = a.shape[:2]
    rows = a.view(np.uint8).reshape(h, -1)
    rows = np.concatenate([rows, np.zeros((h, pad), np.uint8)], 1)
    return TS.types["sensor_msgs/msg/Image"](
        header=TS.types["std_msgs/msg/Header"](
            stamp=TS.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="camera"),
        height=h, width=w, encoding=encoding,
        is_bigendian=int(big), step=rows.shape[1], data=rows.reshape(-1))


def test_same_decoding_for_rosbags_and_rclpy_messages():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    for enc, arr in (("rgb8", rgb), ("bgr8", rgb[:, :, ::-1]), ("mono8", rgb[:, :, 0])):
        rb = rosbags_image(arr, enc, pad=3)
        rc = C.image_to_msg(np.ascontiguousarray(arr), enc)
        np.testing.assert_array_equal(decode_image(rb), decode_image(rc))
        np.testing.assert_array_equal(decode_rgb(rb), C.msg_to_rgb(rc))
    np.testing.assert_array_equal(decode_rgb(rosbags_image(rgb[:, :, ::-1], "BGR8")), rgb)
    alpha = rng.integers(0, 256, (24, 32, 1), dtype=np.uint8)
    for enc, arr in (("rgba8", np.dstack([rgb, alpha])),
                     ("bgra8", np.dstack([rgb[:, :, ::-1], alpha]))):   # alpha dropped
        np.testing.assert_array_equal(decode_rgb(rosbags_image(arr, enc, pad=2)), rgb)
    assert decode_rgb(rosbags_image(rgb[:, :, 0], "mono8"), keep_mono=True).shape == (24, 32)


def test_depth_encodings_and_errors():
    d = np.linspace(0.5, 4.0, 24 * 32, dtype=np.float32).reshape(24, 32)
    d[0, 0] = np.nan
    out = decode_depth(rosbags_image(d, "32FC1", big=True))
    assert out[0, 0] == 0 and np.allclose(out.reshape(-1)[1:], d.reshape(-1)[1:])
    mm = np.round(d[1:] * 1000).astype(np.uint16)
    np.testing.assert_allclose(decode_depth(rosbags_image(mm, "16UC1")), mm / 1000.0, atol=1e-6)
    with pytest.raises(UnsupportedEncoding, match="depth encoding 'rgb8'"):
        decode_depth(rosbags_image(np.zeros((2, 2, 3), np.uint8), "rgb8"))
    bad = rosbags_image(np.zeros((4, 4, 3), np.uint8), "rgb8")
    bad.data = bad.data[:-1]
    with pytest.raises(ConversionError, match="bytes, expected"):
        decode_image(bad)
    f = encode_image(d)
    assert (f.encoding, f.step, f.data.size) == ("32FC1", 32 * 4, d.nbytes)


def test_camera_info_both_message_kinds():
    rb = bagio.camera_info_msg(TS, K, 0)
    rc = C.intrinsics_to_camera_info(K)
    assert camera_info_to_intrinsics(rb) == camera_info_to_intrinsics(rc) == K
    assert C.camera_info_to_intrinsics is camera_info_to_intrinsics
    rb.k = np.zeros(9)
    with pytest.raises(ConversionError, match="uncalibrated"):
        camera_info_to_intrinsics(rb)


def test_bag_file_raw_and_decoded(tmp_path):
    from splat_slam_synth import generate_sequence
    from splat_slam_ros.io.datasets import open_dataset
    seq = generate_sequence("builtin", 3, "32x24", tmp_path / "seq", progress=False)
    bagio.write_bag(open_dataset(seq), tmp_path / "bag", progress=False)
    bag = BagFile(tmp_path / "bag")
    img_topic = bagio.DEFAULT_TOPICS["image"]
    assert bag.topics()[img_topic] == ("sensor_msgs/msg/Image", 3)
    assert bag.info["format"] == "tum"
    raw = list(bag.raw_messages([img_topic]))
    dec = list(bag.messages([img_topic]))
    assert [t for _, t, _ in raw] == [t for _, t, _ in dec]
    for (_, _, b), (_, _, d) in zip(raw, dec):
        np.testing.assert_array_equal(C.msg_to_rgb(deserialize_message(b, RclpyImage)),
                                      decode_rgb(d()))
    player_reader = BagReader(tmp_path / "bag")
    assert player_reader.counts[img_topic] == 3
    assert player_reader.types[img_topic] == "sensor_msgs/msg/Image"
    with pytest.raises(PlayerError, match="not a rosbag2 folder"):
        BagReader(tmp_path / "seq")
    with pytest.raises(DatasetError, match="unknown bag backend"):
        BagFile(tmp_path / "bag", backend="sqlite")
