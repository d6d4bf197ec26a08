"""File helpers shared by the folder readers: images, 4x4 poses, ``intrinsics.json``.

Every error is a :class:`DatasetError` whose message starts with the offending file.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated

import numpy as np
from PIL import Image

from shared.datasets.base import DatasetError
from shared.geometry import Intrinsics, Pose, is_rigid

_DIGITS = re.compile(r"(\d+)")
# Pillow reports 16-bit PNGs in one of these modes depending on byte order.
_UINT16_MODES = {"I;16", "I;16L", "I;16B", "I;16N"}


def natural_key(path: Path) -> tuple:
    """Sort key that puts ``frame2`` before ``frame10`` (HM3D walks are not zero-padded)."""
    parts = _DIGITS.split(path.name)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in parts)


def require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise DatasetError(f"{path}: {what} folder not found")
    return path


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found")
    return path


def _open_image(path: Path) -> Image.Image:
    """Decode fully now, so a truncated file fails here with its name, not later."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    if size == 0:
        raise DatasetError(f"{path}: empty image file (0 bytes)")
    try:
        with Image.open(path) as im:
            im.load()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise DatasetError(f"{path}: unreadable or truncated image ({e})") from e
    if im.width == 0 or im.height == 0:
        raise DatasetError(f"{path}: zero-size image ({im.width}x{im.height})")
    return im


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the header only."""
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DatasetError(f"{path}: image file not found") from None
    except (OSError, SyntaxError, ValueError) as e:
        raise DatasetError(f"{path}: unreadable image ({e})") from e


def read_rgb(path: Path) -> Annotated[np.ndarray, "(H, W, 3) uint8"]:
    im = _open_image(path)
    if im.mode.startswith(("I", "F")):
        raise DatasetError(f"{path}: expected a colour image, got a {im.mode} (depth-like) image")
    if im.mode != "RGB":
        im = im.convert("RGB")
    return np.array(im, dtype=np.uint8)


def read_uint16(path: Path, what: str = "depth") -> Annotated[np.ndarray, "(H, W) uint16"]:
    """A 16-bit single-channel PNG (depth in units, or instance ids + 1)."""
    return uint16_pixels(_open_image(path), str(path), what)


def uint16_pixels(im: Image.Image, where: str, what: str = "depth") -> Annotated[np.ndarray, "(H, W) uint16"]:
    """The values of a decoded 16-bit single-channel image (Pillow gives I;16 or I)."""
    if im.mode in _UINT16_MODES:
        return np.asarray(im).astype(np.uint16)
    if im.mode == "I":
        a = np.asarray(im)
        if a.size and (a.min() < 0 or a.max() > 65535):
            raise DatasetError(f"{where}: {what} values outside the 16-bit range")
        return a.astype(np.uint16)
    raise DatasetError(f"{where}: expected a 16-bit single-channel {what} PNG, got mode {im.mode}")


def check_size(
    path: Path, array: Annotated[np.ndarray, "(H, W, ...)"], width: int, height: int, against: str
) -> None:
    h, w = array.shape[:2]
    if (w, h) != (width, height):
        raise DatasetError(f"{path}: image is {w}x{h} but {against} is {width}x{height}")


def checked_pose(T: Annotated[np.ndarray, "(4, 4)"], where: str) -> Pose:
    """``T`` as float64 if it is a finite rigid transform, else a DatasetError naming ``where``."""
    T = np.asarray(T, dtype=np.float64)
    if not np.isfinite(T).all():
        raise DatasetError(f"{where}: pose has NaN or infinite values")
    if not is_rigid(T):
        raise DatasetError(f"{where}: pose is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return T


def parse_floats(text: str, where: str) -> list[float]:
    try:
        return [float(x) for x in text.split()]
    except ValueError as e:
        raise DatasetError(f"{where}: not a list of numbers ({e})") from None


def read_pose_file(path: Path) -> Pose:
    """A 4x4 matrix written as 16 numbers, on one line or four (row-major)."""
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read pose file ({e})") from e
    values = parse_floats(text, str(path))
    if len(values) != 16:
        raise DatasetError(f"{path}: expected 16 numbers (a 4x4 pose), found {len(values)}")
    return checked_pose(np.array(values).reshape(4, 4), str(path))


def load_intrinsics_json(path: Path) -> tuple[Intrinsics, float | None]:
    """``{"fx", "fy", "cx", "cy", "width", "height"[, "depth_scale"]}`` -> intrinsics, scale."""
    try:
        data = json.loads(path.read_text())
        K = Intrinsics(**{k: data[k] for k in ("fx", "fy", "cx", "cy", "width", "height")})
        scale = data.get("depth_scale")
        if scale is not None and not (isinstance(scale, int | float) and scale > 0):
            raise ValueError(f"depth_scale must be a positive number, got {scale!r}")
    except (OSError, ValueError, KeyError, TypeError) as e:
        detail = f"missing key {e}" if isinstance(e, KeyError) else str(e)
        raise DatasetError(f"{path}: invalid intrinsics file ({detail})") from None
    return K, (float(scale) if scale is not None else None)


def check_index(i: int, n: int) -> int:
    if not 0 <= i < n:
        raise IndexError(f"frame {i} out of range (sequence has {n} frames)")
    return i
