"""Field-level codec of ``sensor_msgs/Image`` and ``sensor_msgs/CameraInfo``.

One set of encoding rules for every message source: rosbags and mcap_ros2 objects (bag
reading, :mod:`splat_slam_ros.io.bagio`) and rclpy messages (the nodes, ``nodes/convert.py``)
expose the same fields (``encoding``, ``height``, ``width``, ``step``, ``is_bigendian``,
``data``; ``k``, ``d``, ``distortion_model``), so the decoders only read those.

Encodings (case-insensitive on input, canonical names on output): rgb8, bgr8, rgba8, bgra8,
mono8, 8UC1, mono16, 16UC1, 32FC1. Depth: 32FC1 metres or 16UC1/mono16 millimetres (REP-118).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

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
    "mono16": (np.uint16, 1),
    "16UC1": (np.uint16, 1),
    "32FC1": (np.float32, 1),
}
_CANONICAL = {k.lower(): k for k in ENCODINGS}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1")


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


def to_rgb(a: np.ndarray, encoding: str, keep_mono: bool = False) -> np.ndarray:
    """A decoded 8-bit colour/mono image -> H x W x 3 uint8 RGB (a new array); with
    ``keep_mono`` a mono image stays H x W."""
    enc = canonical_encoding(encoding)
    if enc == "rgb8":
        return a.copy()
    if enc == "bgr8":
        return np.ascontiguousarray(a[:, :, ::-1])
    if enc == "rgba8":
        return np.ascontiguousarray(a[:, :, :3])
    if enc == "bgra8":
        return np.ascontiguousarray(a[:, :, 2::-1])
    if enc in ("mono8", "8UC1"):
        return a.copy() if keep_mono else np.repeat(a[:, :, None], 3, axis=2)
    raise UnsupportedEncoding(f"image encoding {encoding!r} is not a colour image "
                              "(expected rgb8, bgr8, rgba8, bgra8 or mono8)")


def decode_rgb(msg, keep_mono: bool = False) -> np.ndarray:
    """Image fields of a colour/mono 8-bit encoding -> H x W x 3 uint8 RGB (a copy)."""
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
