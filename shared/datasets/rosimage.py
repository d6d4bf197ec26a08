"""sensor_msgs/Image and CompressedImage payloads to numpy arrays (no cv_bridge needed).

Compressed images follow image_transport's conventions. ``compressed``: the ``format`` field
reads ``"<raw encoding>; <jpeg|png> compressed <target>"`` (older publishers write just
``"jpeg"``), the data is an ordinary JPEG or PNG file. ``compressedDepth``
(compressed_depth_image_transport): ``"16UC1; compressedDepth png"`` or
``"32FC1; compressedDepth"`` (no codec: png), the data is a 12-byte ConfigHeader (int32
compression format, float32 depthQuantA, float32 depthQuantB, little-endian) followed by a
16-bit PNG: the depth itself for 16UC1, quantised inverse depth for 32FC1
(``depth = depthQuantA / (value - depthQuantB)``, 0 = no reading).

Network images are untrusted: a compressed image whose header claims more than
:data:`MAX_PIXELS` pixels is refused before any pixel is decoded (a decompression bomb),
and only Pillow's JPEG and PNG parsers are ever offered the bytes.
"""

from __future__ import annotations

import io
import math
import re
import struct
from typing import Annotated, Any

import numpy as np
from PIL import Image

from shared.datasets.base import DatasetError
from shared.datasets.files import uint16_pixels

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
MAX_PIXELS = 4096 * 4096
"""Largest compressed image decoded; a header claiming more is refused before decoding."""
CONFIG_HEADER_BYTES = 12
"""compressed_depth_image_transport's ConfigHeader: int32 format, float32 depthParam[2]."""

_COLOUR_CODECS = {"jpeg": "JPEG", "jpg": "JPEG", "png": "PNG"}
_COLOUR_FORMATS = ("JPEG", "PNG")
_ENCODING_WORD = re.compile(r"^((rgb|bgr|rgba|bgra|mono|bayer_[a-z]+)\d+|\d+(uc|sc|fc)\d)$")


class UnsupportedEncodingError(DatasetError):
    """A well-formed image in an encoding or compression format that cannot be decoded here."""


def is_compressed(msg: Any) -> bool:
    """True for a sensor_msgs/CompressedImage (it has ``format``, not ``encoding``)."""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def compressed_format(msg: Any) -> tuple[str, str]:
    """(raw encoding, codec) of a CompressedImage's ``format`` field. The raw encoding is
    lower case, "" when the publisher did not say it. The codec is ``jpeg``, ``png``,
    ``compressedDepth png``, ``compressedDepth rvl``, "" (unstated: the data's own header
    tells) or the unknown word found (``tiff``, ``h264``: not decoded here)."""
    fmt = str(msg.format).strip()
    enc, sep, rest = fmt.partition(";")
    if not sep:  # old publishers: the format is the codec alone ("jpeg")
        enc, rest = "", fmt
    words = rest.lower().replace(",", " ").split()
    if "compresseddepth" in words:
        # image_transport: a bare "compressedDepth" (before RVL existed) means png
        return enc.strip().lower(), "compressedDepth rvl" if "rvl" in words else "compressedDepth png"
    for w in words:
        if w in _COLOUR_CODECS:
            return enc.strip().lower(), "jpeg" if w == "jpg" else w
    # the codec is the word that is neither "compressed" nor an encoding ("bgr8; compressed bgr8": unstated)
    other = [w for w in words if w != "compressed" and not _ENCODING_WORD.match(w)]
    return enc.strip().lower(), other[0] if other else ""


def _open(data: bytes, where: str, formats: tuple[str, ...]) -> Image.Image:
    """A compressed image's header, checked against :data:`MAX_PIXELS` (not yet decoded)."""
    try:
        im = Image.open(io.BytesIO(data), formats=list(formats))
    except Image.DecompressionBombError as e:
        raise DatasetError(f"{where}: compressed image refused, its header claims too many pixels ({e})") from None
    except (OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"{where}: unreadable compressed image ({e})") from None
    w, h = im.size
    if w == 0 or h == 0:
        raise DatasetError(f"{where}: zero-size image ({w}x{h})")
    if w * h > MAX_PIXELS:
        raise DatasetError(f"{where}: compressed image claims {w}x{h} pixels, more than the limit of {MAX_PIXELS}")
    return im


def _load(im: Image.Image, where: str) -> Image.Image:
    try:
        im.load()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise DatasetError(f"{where}: unreadable compressed image ({e})") from None
    return im


def _colour_image(msg: Any, where: str) -> Image.Image:
    """The header of a JPEG/PNG colour CompressedImage; UnsupportedEncodingError otherwise."""
    _, codec = compressed_format(msg)
    if codec.startswith("compressedDepth"):
        raise UnsupportedEncodingError(f"{where}: format {msg.format!r} is compressed depth, not a colour image (expected JPEG or PNG)")
    if codec and codec not in _COLOUR_CODECS:
        raise UnsupportedEncodingError(f"{where}: compressed format {msg.format!r} is not supported (expected JPEG or PNG)")
    # Either parser, whatever the format says: publishers mislabel, and the bytes' own
    # signature picks the parser; no other parser of Pillow's (TIFF...) ever sees network bytes.
    return _open(bytes(msg.data), where, _COLOUR_FORMATS)


def _compressed(msg: Any, where: str) -> Image.Image:
    return _load(_colour_image(msg, where), where)


def _raw(msg: Any, where: str) -> tuple[np.ndarray, str]:
    """(H, W, C) array of an Image message, honouring row padding and byte order."""
    enc, code, ch, h, w, step = _raw_header(msg, where)
    dtype = np.dtype(("<" if not msg.is_bigendian else ">") + code)
    row = w * ch * dtype.itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    rows = data[: step * h].reshape(h, step)[:, :row]
    return np.ascontiguousarray(rows).view(dtype).reshape(h, w, ch).astype(dtype.newbyteorder("=")), enc


def _raw_header(msg: Any, where: str) -> tuple[str, str, int, int, int, int]:
    """Encoding, dtype code, channels, height, width and step of an Image, checked against
    the data it carries (no pixel is read)."""
    enc = str(msg.encoding).lower()
    if enc not in _RAW:
        raise UnsupportedEncodingError(f"{where}: unsupported image encoding {msg.encoding!r}")
    code, ch = _RAW[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise DatasetError(f"{where}: zero-size image ({w}x{h})")
    row = w * ch * np.dtype(code).itemsize
    size = int(getattr(msg.data, "size", None) or len(msg.data))  # a numpy array, or bytes
    if step < row or size < step * h:
        raise DatasetError(f"{where}: image data holds {size} bytes, {w}x{h} {msg.encoding} needs {row * h}")
    return enc, code, ch, h, w, step


def decode_colour(msg: Any, where: str) -> Annotated[np.ndarray, "(H, W, 3) uint8 RGB"]:
    """RGB pixels of a colour Image (rgb8, bgr8, rgba8, bgra8, mono8) or JPEG/PNG
    CompressedImage; DatasetError (UnsupportedEncodingError for a foreign encoding)."""
    if is_compressed(msg):
        # image_transport compresses bgr8 frames into ordinary (RGB) JPEG/PNG files.
        return np.array(_compressed(msg, where).convert("RGB"), dtype=np.uint8)
    a, enc = _raw(msg, where)
    if enc not in COLOUR_ENCODINGS:
        raise UnsupportedEncodingError(f"{where}: {msg.encoding!r} is not a colour encoding ({', '.join(COLOUR_ENCODINGS)})")
    if a.shape[2] == 1:
        return np.repeat(a, 3, axis=2)
    a = a[:, :, :3]
    return np.ascontiguousarray(a[:, :, ::-1] if enc.startswith("bgr") else a)


def _metres_to_mm(a: np.ndarray) -> Annotated[np.ndarray, "(H, W) uint16"]:
    """Float metres to uint16 millimetres; NaN, non-positive and beyond 65.535 m become 0."""
    with np.errstate(invalid="ignore", over="ignore"):
        mm = np.nan_to_num(a.astype(np.float64) * FLOAT_DEPTH_SCALE, nan=0.0, posinf=0.0, neginf=0.0)
    mm = np.rint(mm)
    mm[(mm <= 0) | (mm > 65535)] = 0
    return mm.astype(np.uint16)


def _depth_kind(msg: Any, where: str) -> tuple[str, str]:
    """(raw encoding, codec) of a compressed depth image, refusing what cannot be depth."""
    enc, codec = compressed_format(msg)
    if codec == "compressedDepth rvl":
        raise UnsupportedEncodingError(f"{where}: compressedDepth rvl is not supported; set the publisher's format to png")
    if enc and enc not in ("16uc1", "mono16", "32fc1"):
        raise UnsupportedEncodingError(f"{where}: {msg.format!r} is not a depth encoding ({', '.join(DEPTH_ENCODINGS)})")
    if codec == "compressedDepth png":
        if not enc:
            raise UnsupportedEncodingError(f"{where}: compressedDepth format {msg.format!r} does not say 16UC1 or 32FC1")
        return enc, codec
    if codec not in ("png", ""):
        raise UnsupportedEncodingError(
            f"{where}: compressed depth format {msg.format!r} is not supported (expected compressedDepth, or lossless 16-bit PNG)"
        )
    if enc == "32fc1":
        raise UnsupportedEncodingError(f"{where}: 32FC1 depth in a plain PNG is not supported; use compressedDepth")
    return enc or "16uc1", codec


def _depth_image(msg: Any, where: str) -> tuple[Image.Image, str, tuple[float, float]]:
    """Header of the PNG inside a compressed depth image, its raw encoding and the
    compressedDepth quantisation (depthQuantA, depthQuantB)."""
    enc, codec = _depth_kind(msg, where)
    data = bytes(msg.data)
    quant = (0.0, 0.0)
    if codec == "compressedDepth png":
        if len(data) <= CONFIG_HEADER_BYTES:
            raise DatasetError(
                f"{where}: compressedDepth data of {len(data)} bytes has no image after its {CONFIG_HEADER_BYTES}-byte header"
            )
        _, qa, qb = struct.unpack_from("<iff", data)
        if enc == "32fc1" and not (math.isfinite(qa) and math.isfinite(qb) and qa > 0):
            raise DatasetError(f"{where}: compressedDepth header has invalid quantisation depthQuantA={qa}, depthQuantB={qb}")
        quant = (qa, qb)
        data = data[CONFIG_HEADER_BYTES:]
    return _open(data, where, ("PNG",)), enc, quant


def decode_depth(
    msg: Any, depth_scale: float, where: str
) -> tuple[Annotated[np.ndarray, "(H, W) uint16"], float]:
    """Depth in units and its scale: 16-bit depth keeps ``depth_scale``; 32FC1 metres become
    millimetres, NaN / non-positive / beyond 65.535 m read as 0 (no reading).

    Takes a raw Image, a ``compressedDepth`` CompressedImage (16UC1 or 32FC1, png) or a
    plain 16-bit PNG CompressedImage (image_transport's ``compressed`` on 16UC1)."""
    if is_compressed(msg):
        im, enc, (qa, qb) = _depth_image(msg, where)
        v = uint16_pixels(_load(im, where), where, "depth image")
        if enc != "32fc1":
            return v, depth_scale
        # The inverse-depth quantisation of compressed_depth_image_transport, in float32 as it does.
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.float32(qa) / (v.astype(np.float32) - np.float32(qb))
        d[v == 0] = np.nan
        return _metres_to_mm(d), FLOAT_DEPTH_SCALE
    a, enc = _raw(msg, where)
    if enc not in ("16uc1", "mono16", "32fc1"):
        raise UnsupportedEncodingError(f"{where}: {msg.encoding!r} is not a depth encoding ({', '.join(DEPTH_ENCODINGS)})")
    a = a[:, :, 0]
    if enc != "32fc1":
        return a.astype(np.uint16), depth_scale
    return _metres_to_mm(a), FLOAT_DEPTH_SCALE


def depth_scale_of(msg: Any, configured: float) -> float:
    """The scale :func:`decode_depth` will report for this message's encoding."""
    if is_compressed(msg):
        enc = compressed_format(msg)[0]
    else:
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


def peek_size(msg: Any, role: str, where: str) -> tuple[int, int]:
    """(width, height) of a ``colour`` or ``depth`` image from its header only, after the
    checks that need no pixel: the encoding or format suits the role
    (UnsupportedEncodingError), a raw image carries its bytes, a compressed one's header
    parses and claims at most :data:`MAX_PIXELS` pixels (DatasetError)."""
    if role not in ("colour", "depth"):
        raise ValueError(f"role must be 'colour' or 'depth', not {role!r}")
    if is_compressed(msg):
        im = _colour_image(msg, where) if role == "colour" else _depth_image(msg, where)[0]
        return im.size
    enc, _, _, h, w, _ = _raw_header(msg, where)
    allowed = COLOUR_ENCODINGS if role == "colour" else ("16uc1", "mono16", "32fc1")
    if enc not in allowed:
        names = COLOUR_ENCODINGS if role == "colour" else DEPTH_ENCODINGS
        raise UnsupportedEncodingError(f"{where}: {msg.encoding!r} is not a {role} encoding ({', '.join(names)})")
    return w, h
