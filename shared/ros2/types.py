"""ROS 2 message types without ROS: rosbags' typestore builds, encodes and decodes them.

CDR (de)serialisation and RIHS01 type hashes both come from ``rosbags`` (a maintained,
pure-Python implementation of ROS 2's message definitions); nothing here parses CDR by hand.
A payload from the network is untrusted: :func:`decode` refuses oversized ones before
parsing and turns every failure of the parser into one :class:`RosDecodeError` naming the
type, so a caller counts it and goes on.
"""

from __future__ import annotations

import functools
from typing import Any

from rosbags.typesys import Stores, get_typestore

_STORES = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}

TYPE_HASH_NOT_SUPPORTED = "TypeHashNotSupported"
"""What rmw_zenoh on Humble (no type descriptions) puts in a key instead of a hash."""


class RosDecodeError(ValueError):
    """A payload that is not a valid CDR message of the expected type."""


@functools.cache
def typestore(distro: str = "jazzy") -> Any:
    """The message definitions of one ROS 2 distribution."""
    try:
        return get_typestore(_STORES[distro])
    except KeyError:
        raise ValueError(f"unknown ROS 2 distro {distro!r}; expected one of {', '.join(_STORES)}") from None


def msg_class(ros_type: str, distro: str = "jazzy") -> Any:
    """The Python class of ``ros_type`` (``sensor_msgs/msg/Image``); KeyError if unknown."""
    try:
        return typestore(distro).types[ros_type]
    except KeyError:
        raise KeyError(f"ROS 2 message type {ros_type!r} is not in {distro}'s definitions") from None


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the name rmw_zenoh
    puts in keys and liveliness tokens)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ValueError(f"{ros_type!r} is not a ROS 2 type name like sensor_msgs/msg/Image")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str:
    """Inverse of :func:`dds_type_name`."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or not all(parts):
        raise ValueError(f"{dds_type!r} is not a DDS type name like sensor_msgs::msg::dds_::Image_")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


@functools.cache
def type_hash(ros_type: str, distro: str = "jazzy") -> str:
    """The RIHS01 hash of ``ros_type`` in ``distro`` (``RIHS01_<64 hex>``), as ROS 2 computes
    it from the type description; Humble has none (:data:`TYPE_HASH_NOT_SUPPORTED`)."""
    if distro == "humble":
        return TYPE_HASH_NOT_SUPPORTED
    msg_class(ros_type, distro)
    return typestore(distro).hash_rihs01(ros_type)


def encode(msg: Any, ros_type: str | None = None, distro: str = "jazzy") -> bytes:
    """CDR bytes (little-endian, with the 4-byte encapsulation header) of ``msg``."""
    name = ros_type or msg.__msgtype__
    return bytes(typestore(distro).serialize_cdr(msg, name))


def decode(payload: bytes | bytearray | memoryview, ros_type: str, distro: str = "jazzy", *, max_bytes: int | None = None) -> Any:
    """The ``ros_type`` message in ``payload``; :class:`RosDecodeError` if it is not one."""
    n = len(payload)
    if max_bytes is not None and n > max_bytes:
        raise RosDecodeError(f"{ros_type}: payload of {n} bytes exceeds the limit of {max_bytes}")
    if n < 4:
        raise RosDecodeError(f"{ros_type}: payload of {n} bytes has no CDR header")
    if bytes(payload[:2]) not in (b"\x00\x00", b"\x00\x01"):
        raise RosDecodeError(f"{ros_type}: CDR encapsulation {bytes(payload[:2]).hex()} is not plain CDR (0000 or 0001)")
    msg_class(ros_type, distro)  # an unknown type is the caller's error, not the payload's
    try:
        return typestore(distro).deserialize_cdr(bytes(payload), ros_type)
    except Exception as e:  # the parser raises many kinds on hostile bytes: one error for callers
        raise RosDecodeError(f"{ros_type}: invalid CDR payload of {n} bytes ({type(e).__name__}: {e})") from None
