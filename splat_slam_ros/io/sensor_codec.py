"""Field-level codec of ``sensor_msgs/Image`` and ``sensor_msgs/CameraInfo``.

One set of encoding rules for every message source: rosbags and mcap_ros2 objects (bag
reading, :mod:`splat_slam_ros.io.bagio`) and rclpy messages (the nodes, ``nodes/convert.py``)
expose the same fields (``encoding``, ``height``, ``width``, ``step``, ``is_bigendian``,
``data``; ``k``, ``d``, ``distortion_model``), so the decoders only read those.

Encodings (case-insensitive on input, canonical names on output): rgb8, bgr8, rgba8, bgra8,
mono8, 8UC1, the 16-bit ones (rgb16, bgr16, rgba16, bgra16 and, as a camera image, mono16:
the full 16-bit range scaled to 8 bits, as cv_bridge does),
the 8-bit Bayer mosaics (bayer_rggb8, bayer_bggr8, bayer_gbrg8, bayer_grbg8: demosaicked with
OpenCV), packed YUV 4:2:2 (yuv422 = uyvy, yuv422_yuy2 = yuyv), mono16, 16UC1, 32FC1. Depth:
32FC1 metres or 16UC1/mono16 millimetres (REP-118).

``sensor_msgs/CompressedImage`` (``format``, ``data``: image_transport's "compressed"
transport, e.g. "rgb8; jpeg compressed bgr8", or a bare "jpeg" / "png") is decoded with
OpenCV by :func:`decode_rgb` as well; its compressedDepth variant is refused.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from splat_slam_ros.types import Intrinsics


class ConversionError(ValueError):
    """A message cannot be converted (size mismatch, garbage data, bad shape)."""


class UnsupportedEncoding(ConversionError):
    """An image encoding this project does not handle."""


# encoding -> (numpy dtype, channels)
ENCODINGS = {
    "rgb8": (np.uint8, 3),
    "bgr8": (np.uint8, 3),
    "rgba8": (np.uint8, 4),
    "bgra8": (np.uint8, 4),
    "mono8": (np.uint8, 1),
    "8UC1": (np.uint8, 1),
    "rgb16": (np.uint16, 3),
    "bgr16": (np.uint16, 3),
    "rgba16": (np.uint16, 4),
    "bgra16": (np.uint16, 4),
    "bayer_rggb8": (np.uint8, 1),
    "bayer_bggr8": (np.uint8, 1),
    "bayer_gbrg8": (np.uint8, 1),
    "bayer_grbg8": (np.uint8, 1),
    "yuv422": (np.uint8, 2),
    "yuv422_yuy2": (np.uint8, 2),
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}
_CANONICAL = {k.lower(): k for k in ENCODINGS}
_CANONICAL.update(uyvy="yuv422", yuyv="yuv422_yuy2")      # the names ROS 2 Jazzy adds
# encoding -> OpenCV conversion to RGB (OpenCV names a Bayer mosaic by its second row)
_TO_RGB = {"bayer_rggb8": cv2.COLOR_BayerBG2RGB, "bayer_bggr8": cv2.COLOR_BayerRG2RGB,
           "bayer_gbrg8": cv2.COLOR_BayerGR2RGB, "bayer_grbg8": cv2.COLOR_BayerGB2RGB,
           "yuv422": cv2.COLOR_YUV2RGB_UYVY, "yuv422_yuy2": cv2.COLOR_YUV2RGB_YUY2}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "mono16", "rgb16",
                    "bgr16", "rgba16", "bgra16") + tuple(_TO_RGB)


def canonical_encoding(encoding: str) -> str:
    """The canonical spelling of a supported encoding; UnsupportedEncoding otherwise."""
    enc = _CANONICAL.get(str(encoding).lower())
    if enc is None:
        raise UnsupportedEncoding(
            f"unsupported image encoding {encoding!r}; supported: {', '.join(ENCODINGS)}")
    return enc


def _bytes(data) -> np.ndarray:
    """The raw bytes of a uint8[] field (numpy array, array.array, bytes or list) as a flat
    uint8 array (a view where the field has a buffer)."""
    if isinstance(data, (list, tuple)):
        data = bytes(data)
    return np.frombuffer(data, np.uint8) if len(data) else np.zeros(0, np.uint8)


def decode_image(msg, copy: bool = True) -> np.ndarray:
    """Image fields -> numpy (H x W for one channel, H x W x C otherwise), in the message's
    own channel order and dtype (native byte order). Handles row padding (``step`` > width x
    pixel size) and big-endian data; ``copy=False`` may return views of the message buffer."""
    enc = canonical_encoding(msg.encoding)
    dtype, ch = ENCODINGS[enc]
    item = np.dtype(dtype).itemsize
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * ch * item
    if step < row:
        raise ConversionError(f"image step {step} < width {w} x {ch * item} bytes per pixel")
    if item > 1 and step % item:
        raise ConversionError(f"image step {step} is not a multiple of the {item}-byte pixel type")
    buf = _bytes(msg.data)
    n = buf.size
    if n != step * h:
        raise ConversionError(f"image data has {n} bytes, expected {step * h} "
                              f"({h} rows x step {step}) for {w}x{h} {enc}")
    if h == 0 or w == 0:
        return np.zeros((h, w) if ch == 1 else (h, w, ch), dtype)
    raw = buf.reshape(h, step)
    copied = False
    if step != row:                              # drop row padding (copies)
        raw = np.ascontiguousarray(raw[:, :row])
        copied = True
    native = np.dtype(dtype)
    dt = native.newbyteorder(">" if msg.is_bigendian else "<") if item > 1 else native
    a = raw.view(dt).reshape((h, w) if ch == 1 else (h, w, ch))
    if dt != native:                             # foreign byte order -> native (copies)
        return a.astype(native)
    return a.copy() if copy and not copied else a


def to_8bit(a: np.ndarray) -> np.ndarray:
    """16-bit intensities -> 8-bit (x / 257, rounded)."""
    return ((a.astype(np.uint32) + 128) // 257).astype(np.uint8)


_SWAP_TO_RGB = {"bgr8": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
                "bgra8": cv2.COLOR_BGRA2RGB}


def to_rgb(a: np.ndarray, encoding: str, keep_mono: bool = False) -> np.ndarray:
    """A decoded colour/mono camera image -> H x W x 3 uint8 RGB (a new array); with
    ``keep_mono`` a mono image stays H x W (a Bayer mosaic is a colour image)."""
    enc = canonical_encoding(encoding)
    if enc in _TO_RGB:
        if a.shape[0] < 2 or a.shape[1] < 2 or (enc.startswith("yuv") and a.shape[1] % 2):
            raise ConversionError(f"a {a.shape[1]}x{a.shape[0]} image cannot be {enc} (a "
                                  "Bayer mosaic needs 2x2 pixels, packed YUV an even width)")
        return cv2.cvtColor(np.ascontiguousarray(a), _TO_RGB[enc])
    if enc.endswith("16") and enc[:-2] in ("rgb", "bgr", "rgba", "bgra", "mono"):
        a, enc = to_8bit(a), enc[:-2] + "8"
    if enc == "rgb8":
        return a.copy()
    if enc in _SWAP_TO_RGB:     # cvtColor: 0.12 ms at 640x480, a reversed-view copy 2.0 ms
        return cv2.cvtColor(np.ascontiguousarray(a), _SWAP_TO_RGB[enc])
    if enc in ("mono8", "8UC1"):
        return a.copy() if keep_mono else np.repeat(a[:, :, None], 3, axis=2)
    raise UnsupportedEncoding(f"image encoding {encoding!r} is not a colour image "
                              f"(expected one of {', '.join(COLOUR_ENCODINGS)})")


def is_compressed(msg) -> bool:
    """A sensor_msgs/CompressedImage (``format`` + ``data``, no ``encoding``)?"""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def is_compressed_topic(topic: str) -> bool:
    """image_transport's naming: the compressed transport of BASE is ``BASE/compressed``."""
    return str(topic).rstrip("/").endswith("/compressed")


def compressed_topic(topic: str) -> str:
    """image_transport's name of a base image topic's compressed transport (a name that
    already ends in ``/compressed`` stays)."""
    return topic if is_compressed_topic(topic) else topic.rstrip("/") + "/compressed"


def decode_compressed(msg, keep_mono: bool = False) -> np.ndarray:
    """CompressedImage fields (``format``, ``data``) -> H x W x 3 uint8 RGB (H x W for a mono
    image with ``keep_mono``). The format is image_transport's ("<encoding>; jpeg compressed
    <encoding>", the second being the order of the compressed colours: OpenCV writes and
    reads BGR) or just the codec ("jpeg", "png")."""
    fmt = str(msg.format).strip()
    if "compresseddepth" in fmt.lower():
        raise UnsupportedEncoding(f"compressed image format {fmt!r} is a depth image "
                                  "(compressedDepth), not a camera image")
    buf = _bytes(msg.data)
    a = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if a is None:
        raise ConversionError(f"cannot decode the compressed image ({buf.size} bytes, format "
                              f"{fmt or 'not given'!r})")
    if a.dtype == np.uint16:
        a = to_8bit(a)
    elif a.dtype != np.uint8:
        raise UnsupportedEncoding(f"compressed image of pixel type {a.dtype} (format {fmt!r})")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 2:
        return to_rgb(a, "mono8", keep_mono)
    m = re.search(r"compressed\s+(\w+)", fmt.lower())
    order = "rgb" if m and m.group(1).startswith("rgb") else "bgr"
    return to_rgb(a, order + ("a8" if a.shape[2] == 4 else "8"), keep_mono)


def encode_jpeg(img: np.ndarray, quality: int) -> tuple:
    """uint8 RGB (H x W x 3) or mono (H x W) -> (format, bytes) of a CompressedImage as
    image_transport writes it (the inverse of :func:`decode_compressed`)."""
    if not 1 <= int(quality) <= 100:
        raise ConversionError(f"JPEG quality {quality} is outside 1..100")
    mono = img.ndim == 2
    ok, buf = cv2.imencode(".jpg", img if mono else
                           cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ConversionError(f"cannot JPEG-encode an image of shape {img.shape}")
    enc = "mono8" if mono else "rgb8"
    return f"{enc}; jpeg compressed {'mono8' if mono else 'bgr8'}", buf.reshape(-1)


def decode_rgb(msg, keep_mono: bool = False) -> np.ndarray:
    """Image fields of a colour/mono camera encoding (or CompressedImage fields) -> H x W x 3
    uint8 RGB (a copy)."""
    if is_compressed(msg):
        return decode_compressed(msg, keep_mono)
    return to_rgb(decode_image(msg, copy=False), msg.encoding, keep_mono)


def decode_depth(msg) -> np.ndarray:
    """Image fields, 32FC1 (metres) or 16UC1 / mono16 (millimetres, REP-118) -> float32
    metres H x W; non-finite values become 0 (unknown)."""
    enc = canonical_encoding(msg.encoding)
    if enc not in ("32FC1", "16UC1", "mono16"):
        raise UnsupportedEncoding(f"unsupported depth encoding {msg.encoding!r} (32FC1 or 16UC1)")
    a = decode_image(msg, copy=True)
    d = a.astype(np.float32) / 1000.0 if enc != "32FC1" else a.astype(np.float32, copy=False)
    d[~np.isfinite(d)] = 0
    return d


@dataclass
class ImageFields:
    """What :func:`encode_image` fills into an Image message (little-endian data)."""
    encoding: str
    height: int
    width: int
    step: int
    data: np.ndarray            # flat uint8, C order


def guess_encoding(img: np.ndarray) -> str:
    """Default encoding by shape/dtype: HxWx3 uint8 -> rgb8, HxWx4 uint8 -> rgba8,
    HxW uint8 -> mono8, HxW uint16 -> 16UC1, HxW float32 -> 32FC1."""
    if img.dtype == np.uint8:
        if img.ndim == 2:
            return "mono8"
        if img.ndim == 3 and img.shape[2] in (1, 3, 4):
            return {1: "mono8", 3: "rgb8", 4: "rgba8"}[img.shape[2]]
    elif img.ndim == 2 and img.dtype == np.uint16:
        return "16UC1"
    elif img.ndim == 2 and img.dtype == np.float32:
        return "32FC1"
    raise UnsupportedEncoding(f"no image encoding for an array of shape {img.shape} and dtype "
                              f"{img.dtype}; pass encoding= one of {', '.join(ENCODINGS)}")


def encode_image(img: np.ndarray, encoding: Optional[str] = None) -> ImageFields:
    """numpy image -> Image fields. The array must already be in the channel order
    ``encoding`` names (no colour conversion here); ``encoding`` defaults by shape/dtype."""
    img = np.asarray(img)
    enc = guess_encoding(img) if encoding is None else canonical_encoding(encoding)
    dtype, ch = ENCODINGS[enc]
    if img.ndim == 3 and ch == 1 and img.shape[2] == 1:
        img = img[:, :, 0]
    want_ndim = 2 if ch == 1 else 3
    if img.ndim != want_ndim or (ch > 1 and img.shape[2] != ch):
        raise ConversionError(f"array of shape {img.shape} does not fit encoding {enc} "
                              f"({ch} channel{'s' if ch > 1 else ''})")
    if img.dtype != dtype:
        raise ConversionError(f"array dtype {img.dtype} does not fit encoding {enc} "
                              f"({np.dtype(dtype).name})")
    le = np.ascontiguousarray(img, dtype=np.dtype(dtype).newbyteorder("<"))
    h, w = int(img.shape[0]), int(img.shape[1])
    return ImageFields(enc, h, w, w * ch * np.dtype(dtype).itemsize, le.view(np.uint8).reshape(-1))


def camera_info_to_intrinsics(msg) -> Intrinsics:
    """CameraInfo fields -> Intrinsics (from K; D and distortion_model kept)."""
    k = [float(x) for x in np.asarray(msg.k, dtype=np.float64).reshape(-1)]
    if len(k) != 9 or k[0] <= 0 or k[4] <= 0:
        fx, fy = (k[0], k[4]) if len(k) == 9 else (None, None)
        raise ConversionError(f"CameraInfo has no valid K (fx={fx}, fy={fy}): "
                              "the camera is uncalibrated")
    if msg.width <= 0 or msg.height <= 0:
        raise ConversionError(f"CameraInfo has no image size ({msg.width}x{msg.height})")
    return Intrinsics(k[0], k[4], k[2], k[5], int(msg.width), int(msg.height),
                      msg.distortion_model or "plumb_bob",
                      [float(x) for x in np.asarray(msg.d, dtype=np.float64).reshape(-1)])
