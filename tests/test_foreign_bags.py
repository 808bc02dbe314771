"""Camera images as robots record and publish them: the colour encodings of camera drivers
(Bayer mosaics, packed YUV 4:2:2, 16-bit colour), image_transport's CompressedImage, and
rosbag2 bags recorded elsewhere (their own topic names, compressed images, no camera_info)
read by splat-slam-convert / splat-slam-run."""
import cv2
import numpy as np
import pytest

from splat_slam_nodes import convert as C
from splat_slam_ros.cli.convert import main as convert_main
from splat_slam_ros.io import bagio
from splat_slam_ros.io.bagio import BagDataset
from splat_slam_ros.io.dataset_base import DatasetError
from splat_slam_ros.io.datasets import open_dataset
from splat_slam_ros.io.sensor_codec import (ConversionError, UnsupportedEncoding, decode_rgb,
                                            is_compressed_topic, to_rgb)
from splat_slam_ros.types import Intrinsics

TS = bagio.make_typestore(project_types=False)
K = Intrinsics(40.0, 40.0, 15.5, 11.5, 32, 24)


def scene(k: int = 0) -> np.ndarray:
    """A smooth colour image (32x24 RGB), shifted by ``k`` pixels: demosaicking and 4:2:2
    chroma keep it to a few levels."""
    y, x = np.mgrid[0:24, 0:32].astype(np.float32)
    x = x + k
    return np.stack([128 + 90 * np.sin(x / 6), 128 + 90 * np.cos(y / 5), 60 + 2 * x + y],
                    -1).clip(0, 255).astype(np.uint8)


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic ``pattern`` (e.g. "rggb": R at (0, 0), B at (1, 1)) of an RGB image."""
    m = np.zeros(rgb.shape[:2], np.uint8)
    for i, c in enumerate(pattern):
        m[i // 2::2, i % 2::2] = rgb[i // 2::2, i % 2::2, "rgb".index(c)]
    return m


def packed_422(rgb: np.ndarray, order: str) -> np.ndarray:
    """BT.601 video-range YUV 4:2:2 packed as ``order`` ("uyvy" or "yuyv"), H x W x 2."""
    r, g, b = (rgb[..., i].astype(np.float64) for i in range(3))
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    uv = np.empty_like(y)
    uv[:, 0::2] = (u[:, 0::2] + u[:, 1::2]) / 2
    uv[:, 1::2] = (v[:, 0::2] + v[:, 1::2]) / 2
    pair = (uv, y) if order == "uyvy" else (y, uv)
    return np.stack(pair, -1).round().clip(0, 255).astype(np.uint8)


def compressed(ts, rgb: np.ndarray, fmt: str, ns: int = 0, codec: str = ".png"):
    """A rosbags CompressedImage as image_transport writes it (BGR order into the codec)."""
    img = rgb if rgb.ndim == 2 else (rgb if "compressed rgb" in fmt else rgb[:, :, ::-1])
    ok, buf = cv2.imencode(codec, np.ascontiguousarray(img))
    assert ok
    return ts.types[bagio.T_COMPRESSED](header=bagio._header(ts, ns, "camera"), format=fmt,
                                        data=buf.reshape(-1))


def test_bayer_mosaics_demosaic_to_their_colours():
    rgb = scene()
    for pattern in ("rggb", "bggr", "gbrg", "grbg"):
        out = C.msg_to_rgb(C.image_to_msg(mosaic(rgb, pattern), f"bayer_{pattern}8"))
        # inside the border a smooth image comes back within a few levels; a wrong pattern
        # swaps or mixes channels (tens of levels)
        err = np.abs(out[2:-2, 2:-2].astype(int) - rgb[2:-2, 2:-2]).mean(axis=(0, 1))
        assert (err < 6).all(), (pattern, err)
    with pytest.raises(ConversionError, match=r"1x1 image cannot be bayer_rggb8"):
        to_rgb(np.zeros((1, 1), np.uint8), "bayer_rggb8")


def test_packed_yuv_422_and_16_bit_colour():
    rgb = scene()
    for enc, order in (("yuv422", "uyvy"), ("uyvy", "uyvy"), ("yuv422_yuy2", "yuyv"),
                       ("YUYV", "yuyv")):
        out = to_rgb(packed_422(rgb, order), enc)
        err = np.abs(out.astype(int) - rgb).mean(axis=(0, 1))
        assert (err < 4).all(), (enc, err)
    swapped = to_rgb(packed_422(rgb, "yuyv"), "yuv422")      # the other byte order is garbage
    assert np.abs(swapped.astype(int) - rgb).mean() > 30
    with pytest.raises(ConversionError, match=r"an even width"):
        to_rgb(np.zeros((2, 3, 2), np.uint8), "yuv422")
    wide = rgb.astype(np.uint16) * 257
    np.testing.assert_array_equal(C.msg_to_rgb(C.image_to_msg(wide, "rgb16")), rgb)
    np.testing.assert_array_equal(
        C.msg_to_rgb(C.image_to_msg(np.ascontiguousarray(wide[:, :, ::-1]), "bgr16")), rgb)
    # a 16-bit mono camera (machine vision, thermal): full range to 8 bits, grey in RGB; the
    # same values as 16UC1 are depth (REP-118), never a camera image
    grey = wide[:, :, 1]
    out = C.msg_to_rgb(C.image_to_msg(grey, "mono16"))
    assert out.shape == rgb.shape and (out == rgb[:, :, 1:2]).all()
    assert (decode_rgb(C.image_to_msg(grey, "mono16"), keep_mono=True) == rgb[:, :, 1]).all()
    with pytest.raises(UnsupportedEncoding, match="'16UC1' is not a colour image"):
        C.msg_to_rgb(C.image_to_msg(grey, "16UC1"))


def test_compressed_images_as_image_transport_writes_them():
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CompressedImage
    rgb = scene()
    for fmt in ("rgb8; png compressed bgr8", "bgr8; png compressed bgr8", "png",
                "rgb8; png compressed rgb8"):
        m = compressed(TS, rgb, fmt)
        np.testing.assert_array_equal(decode_rgb(m), rgb)
        # the same bytes as an rclpy message (the tracker node's subscription)
        r = CompressedImage(format=fmt, data=m.data.tobytes())
        r = deserialize_message(serialize_message(r), CompressedImage)
        np.testing.assert_array_equal(C.msg_to_rgb(r), rgb)
    mono = compressed(TS, rgb[:, :, 1], "mono8; png compressed mono8")
    assert decode_rgb(mono, keep_mono=True).shape == (24, 32)
    np.testing.assert_array_equal(decode_rgb(mono)[:, :, 2], rgb[:, :, 1])
    jpeg = decode_rgb(compressed(TS, rgb, "rgb8; jpeg compressed bgr8", codec=".jpg"))
    assert np.abs(jpeg.astype(int) - rgb).mean() < 8
    bad = compressed(TS, rgb, "jpeg")
    bad.data = bad.data[:40]
    with pytest.raises(ConversionError, match=r"cannot decode the compressed image \(40 bytes"):
        decode_rgb(bad)
    depth = compressed(TS, rgb[:, :, 0], "16UC1; compressedDepth png")
    with pytest.raises(UnsupportedEncoding, match=r"compressedDepth\), not a camera image"):
        decode_rgb(depth)
    assert is_compressed_topic("/cam/image_raw/compressed")
    assert not is_compressed_topic("/cam/compressed_image") and \
        not is_compressed_topic("/cam/image_raw")


def write_robot_bag(path, cameras, n=4, extra=True, info=True, storage="MCAP",
                    stamped=True):
    """A bag as a robot records it: per camera (namespace, kind) an image topic — "png" /
    "jpeg": ``NS/image_raw/compressed`` (CompressedImage), "bayer": ``NS/image_raw``
    (bayer_rggb8) — with ``NS/camera_info`` (``info``), and an unrelated String topic;
    ``stamped`` False: a driver that leaves the images' header stamps at 0."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    w = Writer(path, version=8, storage_plugin=getattr(StoragePlugin, storage))
    w.open()
    conns = {}

    def put(topic, msgtype, msg, ns):
        if topic not in conns:
            conns[topic] = w.add_connection(topic, msgtype, typestore=TS)
        w.write(conns[topic], ns, TS.serialize_cdr(msg, msgtype))
    for i in range(n):
        ns = 1_000_000_000 + i * 50_000_000
        for cam, kind in cameras:
            if info:
                put(f"{cam}/camera_info", bagio.T_INFO, bagio.camera_info_msg(TS, K, ns), ns)
            if kind == "bayer":
                m = bagio._image(TS, mosaic(scene(i), "rggb"), ns, "camera", "bayer_rggb8")
                put(f"{cam}/image_raw", bagio.T_IMAGE, m, ns)
            else:
                m = compressed(TS, scene(i), "rgb8; {} compressed bgr8".format(kind),
                               ns if stamped else 0, ".png" if kind == "png" else ".jpg")
                put(f"{cam}/image_raw/compressed", bagio.T_COMPRESSED, m, ns)
        if extra:
            put("/status", "std_msgs/msg/String", TS.types["std_msgs/msg/String"](data="ok"), ns)
    w.close()
    return path


@pytest.mark.parametrize("storage", ["MCAP", "SQLITE3"])
def test_a_robots_bag_is_read_with_its_own_topics(tmp_path, capsys, storage):
    bag = write_robot_bag(tmp_path / "robot", [("/cam0", "png")], storage=storage)
    assert convert_main([str(bag), "--info"]) == 0
    text = capsys.readouterr().out
    assert "camera: /cam0/image_raw/compressed, calibration from /cam0/camera_info" in text
    assert "recorded elsewhere (not by splat-slam-convert)" in text
    ds = open_dataset(bag)
    assert ds.topics["image"] == "/cam0/image_raw/compressed"
    assert ds.topics["camera_info"] == "/cam0/camera_info"
    frames = list(ds)
    assert len(frames) == 4 and frames[1].timestamp == pytest.approx(1.05)
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.image, scene(i))
    # converted into the project's layout: raw rgb8 on /camera/image_raw, the same pixels
    out = tmp_path / "converted"
    assert convert_main([str(bag), "--out", str(out), "--quiet"]) == 0
    assert "/camera/image_raw: 4 messages" in capsys.readouterr().out
    conv = BagDataset(out)
    np.testing.assert_array_equal(list(conv)[3].image, scene(3))
    assert conv.intrinsics.fx == 40.0


def test_a_bag_with_several_cameras_or_no_calibration_says_what_to_choose(tmp_path, capsys):
    bag = write_robot_bag(tmp_path / "two", [("/front", "jpeg"), ("/down", "bayer")])
    with pytest.raises(DatasetError, match=r"bag has 2 image topics \(/down/image_raw, "
                       r"/front/image_raw/compressed\): choose one with --image-topic"):
        open_dataset(bag)
    ds = open_dataset(bag, topics={"image": "/down/image_raw"})
    assert ds.topics["camera_info"] == "/down/camera_info"
    err = np.abs(list(ds)[0].image[2:-2, 2:-2].astype(int) - scene(0)[2:-2, 2:-2]).mean()
    assert err < 6
    assert convert_main([str(bag), "--out", str(tmp_path / "f"), "--quiet", "--image-topic",
                         "/front/image_raw/compressed"]) == 0
    assert convert_main([str(bag), "--info", "--image-topic", "/down/camera_info"]) == 2
    assert "topic /down/camera_info is a sensor_msgs/msg/CameraInfo, not a" in \
        capsys.readouterr().err
    # no camera_info in the bag: the calibration comes from --intrinsics
    bare = write_robot_bag(tmp_path / "bare", [("/cam", "png")], info=False, extra=False)
    assert convert_main([str(bare), "--info"]) == 2
    assert "no camera_info topic for /cam/image_raw/compressed (camera_info topics: none): " \
           "choose one with --camera-info-topic TOPIC, or give the calibration with " \
           "--intrinsics FILE" in capsys.readouterr().err
    calib = tmp_path / "calib.yaml"
    K.to_yaml(calib)
    assert convert_main([str(bare), "--out", str(tmp_path / "g"), "--quiet",
                         "--intrinsics", str(calib)]) == 0
    assert BagDataset(tmp_path / "g").intrinsics.cx == 15.5
    # the topic options are for bags
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "000.png"), scene())
    assert convert_main([str(tmp_path / "imgs"), "--info", "--intrinsics", str(calib),
                         "--image-topic", "/x"]) == 2
    assert "--image-topic / --camera-info-topic apply to bags only" in capsys.readouterr().err


def test_a_frame_that_does_not_decode_is_a_one_line_error(tmp_path, capsys):
    from rosbags.rosbag2 import StoragePlugin, Writer
    w = Writer(tmp_path / "bad", version=8, storage_plugin=StoragePlugin.MCAP)
    w.open()
    ci = w.add_connection("/cam/camera_info", bagio.T_INFO, typestore=TS)
    im = w.add_connection("/cam/image_raw/compressed", bagio.T_COMPRESSED, typestore=TS)
    for i in range(3):
        ns = 10**9 + i * 10**8
        m = compressed(TS, scene(i), "jpeg", ns, ".jpg")
        if i == 2:
            m.data = m.data[:100]                 # a torn frame
        w.write(ci, ns, TS.serialize_cdr(bagio.camera_info_msg(TS, K, ns), bagio.T_INFO))
        w.write(im, ns, TS.serialize_cdr(m, bagio.T_COMPRESSED))
    w.close()
    assert convert_main([str(tmp_path / "bad"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "error: image 2 on /cam/image_raw/compressed: cannot decode the compressed image " \
           "(100 bytes, format 'jpeg')" in err
    assert not (tmp_path / "o").exists()


def test_converted_with_jpeg_images(tmp_path, capsys):
    """``splat-slam-convert --jpeg Q``: image_transport's compressed layout, read back like
    any bag (the bag info names the topic), close to the source at quality 95."""
    src = write_robot_bag(tmp_path / "robot", [("/cam0", "png")], n=3)
    out = tmp_path / "small"
    assert convert_main([str(src), "--out", str(out), "--quiet", "--jpeg", "95"]) == 0
    assert "/camera/image_raw/compressed: 3 messages" in capsys.readouterr().out
    ds = BagDataset(out)
    assert ds.topics["image"] == "/camera/image_raw/compressed"
    assert ds.topic_counts()["/camera/image_raw/compressed"][0] == bagio.T_COMPRESSED
    for i, f in enumerate(ds):
        assert np.abs(f.image.astype(int) - scene(i)).mean() < 3
    assert convert_main([str(src), "--out", str(tmp_path / "q"), "--quiet", "--jpeg", "0"]) == 2
    assert "JPEG quality 0 is outside 1..100" in capsys.readouterr().err


def test_images_without_a_stamp_take_the_bags_log_time(tmp_path, capsys):
    """A driver that never set the header stamp: read (and replayed by the player) with the
    recorder's log time, so the frames keep their order and spacing."""
    from splat_slam_nodes.tools.bag_player import BagReader, cdr_stamp_ns, frames
    bag = write_robot_bag(tmp_path / "nostamp", [("/cam", "png")], n=3, stamped=False)
    ds = open_dataset(bag)
    assert [f.timestamp for f in ds] == pytest.approx([1.0, 1.05, 1.1])
    assert capsys.readouterr().err.count("images without a header stamp: stamped with the " \
                                         "bag's log time") == 1
    groups = list(frames(BagReader(bag), ["/cam/image_raw/compressed", "/cam/camera_info"],
                         "/cam/image_raw/compressed"))
    assert [cdr_stamp_ns(dict(g)["/cam/image_raw/compressed"]) for _t, g in groups] == \
        [10**9, 10**9 + 5 * 10**7, 10**9 + 10**8]
    assert convert_main([str(bag), "--out", str(tmp_path / "c"), "--quiet"]) == 0
