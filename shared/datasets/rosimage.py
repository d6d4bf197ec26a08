"""sensor_msgs/Image and CompressedImage payloads to numpy arrays (no cv_bridge needed)."""

from __future__ import annotations

import io
from typing import Annotated, Any

import numpy as np
from PIL import Image

from shared.datasets.base import DatasetError

# encoding -> (numpy little-endian dtype, channels)
_RAW = {
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
    "mono8": ("u1", 1),
    "16uc1": ("u2", 1),
    "mono16": ("u2", 1),
    "32fc1": ("f4", 1),
}
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
FLOAT_DEPTH_SCALE = 1000.0
"""32FC1 depth (metres) becomes uint16 millimetres."""


def _raw(msg: Any, where: str) -> tuple[np.ndarray, str]:
    """(H, W, C) array of an Image message, honouring row padding and byte order."""
    enc = str(msg.encoding).lower()
    if enc not in _RAW:
        raise DatasetError(f"{where}: unsupported image encoding {msg.encoding!r}")
    code, ch = _RAW[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise DatasetError(f"{where}: zero-size image ({w}x{h})")
    dtype = np.dtype(("<" if not msg.is_bigendian else ">") + code)
    row = w * ch * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or data.size < step * h:
        raise DatasetError(f"{where}: image data holds {data.size} bytes, {w}x{h} {msg.encoding} needs {row * h}")
    rows = data[: step * h].reshape(h, step)[:, :row]
    return np.ascontiguousarray(rows).view(dtype).reshape(h, w, ch).astype(dtype.newbyteorder("=")), enc


def _compressed(msg: Any, where: str) -> Image.Image:
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise DatasetError(f"{where}: compressedDepth images are not supported; record raw depth")
    try:
        im = Image.open(io.BytesIO(bytes(msg.data)))
        im.load()
    except (OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"{where}: unreadable compressed image ({e})") from e
    if im.width == 0 or im.height == 0:
        raise DatasetError(f"{where}: zero-size image")
    return im


def is_compressed(msg: Any) -> bool:
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def decode_colour(msg: Any, where: str) -> Annotated[np.ndarray, "(H, W, 3) uint8 RGB"]:
    if is_compressed(msg):
        # image_transport compresses bgr8 frames into ordinary (RGB) JPEG/PNG files.
        return np.array(_compressed(msg, where).convert("RGB"), dtype=np.uint8)
    a, enc = _raw(msg, where)
    if enc not in COLOUR_ENCODINGS:
        raise DatasetError(f"{where}: {msg.encoding!r} is not a colour encoding ({', '.join(COLOUR_ENCODINGS)})")
    if a.shape[2] == 1:
        return np.repeat(a, 3, axis=2)
    a = a[:, :, :3]
    return np.ascontiguousarray(a[:, :, ::-1] if enc.startswith("bgr") else a)


def decode_depth(
    msg: Any, depth_scale: float, where: str
) -> tuple[Annotated[np.ndarray, "(H, W) uint16"], float]:
    """Depth in units and its scale: 16-bit depth keeps ``depth_scale``; 32FC1 metres become
    millimetres, NaN / non-positive / beyond 65.535 m read as 0 (no reading)."""
    if is_compressed(msg):
        raise DatasetError(f"{where}: compressed depth is not supported; record raw 16UC1 or 32FC1 depth")
    a, enc = _raw(msg, where)
    if enc not in ("16uc1", "mono16", "32fc1"):
        raise DatasetError(f"{where}: {msg.encoding!r} is not a depth encoding ({', '.join(DEPTH_ENCODINGS)})")
    a = a[:, :, 0]
    if enc != "32fc1":
        return a.astype(np.uint16), depth_scale
    mm = np.nan_to_num(a.astype(np.float64) * FLOAT_DEPTH_SCALE, nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.rint(mm)
    mm[(mm <= 0) | (mm > 65535)] = 0
    return mm.astype(np.uint16), FLOAT_DEPTH_SCALE


def depth_scale_of(msg: Any, configured: float) -> float:
    """The scale :func:`decode_depth` will report for this message's encoding."""
    enc = str(getattr(msg, "encoding", "")).lower()
    return FLOAT_DEPTH_SCALE if enc == "32fc1" else configured


def image_size(msg: Any, where: str) -> tuple[int, int]:
    """(width, height) of a colour message, decoding a compressed one."""
    if is_compressed(msg):
        return _compressed(msg, where).size
    w, h = int(msg.width), int(msg.height)
    if w == 0 or h == 0:
        raise DatasetError(f"{where}: zero-size image ({w}x{h})")
    return w, h
