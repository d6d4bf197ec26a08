"""Zenoh keys, attachments and liveliness tokens of ROS 2 traffic, without zenoh or ROS.

Two conventions put ROS 2 topics on Zenoh (docs/ros2.md):

- ``rmw_zenoh`` (ROS 2 itself over Zenoh, rmw_zenoh's docs/design.md): data goes on
  ``<domain_id>/<topic>/<dds type>/<RIHS01 hash>``, e.g.
  ``0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...1a18``, with an attachment
  (int64 sequence number, int64 source timestamp, 16-byte publisher GID). Every node and
  endpoint announces itself with a liveliness token under the hermetic ``@ros2_lv`` prefix
  (``@ros2_lv/<domain>/<zid>/<node_id>/<entity_id>/<kind>/<enclave>/<ns>/<node>/...``) that
  ``ros2 topic list`` reads; names in tokens are mangled ('/' -> '%').
- ``bridge`` (``zenoh-bridge-ros2dds`` in front of a DDS graph): the key is the topic name
  without its leading '/', under the bridge's namespace prefix if it has one; no type, no
  hash, no attachment, no tokens.
"""

from __future__ import annotations

import logging
import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from shared.ros2.types import TYPE_HASH_NOT_SUPPORTED, dds_type_name, ros_type_name, type_hash

log = logging.getLogger(__name__)

Convention = Literal["rmw_zenoh", "bridge"]
"""How ROS 2 topics map onto Zenoh keys (see the module docstring)."""
EntityKind = Literal["NN", "MP", "MS", "SS", "SC"]
"""Node, message publisher, message subscription, service server, service client."""

ADMIN_SPACE = "@ros2_lv"
"""First chunk of every rmw_zenoh liveliness token (a hermetic Zenoh namespace: ``*`` and
``**`` never match it, so tokens must be asked for by this exact prefix)."""

GID_SIZE = 16
"""Bytes in a publisher/client GID on the wire (rmw_zenoh's RMW_GID_STORAGE_SIZE)."""

RMW_ZENOH_DEFAULT_DEPTH = 42
"""History depth rmw_zenoh takes as its default: it is left out of the QoS string, and a
requested depth of 0 (system default) becomes it."""

_CONVENTIONS = ("rmw_zenoh", "bridge")
_ENDPOINT_KINDS = ("MP", "MS", "SS", "SC")
_NAME_CHUNK = re.compile(r"[A-Za-z0-9_]+")
_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_RIHS01 = re.compile(r"RIHS01_[0-9a-f]{64}")
_INT64 = (-(2**63), 2**63 - 1)
# Characters that make a string a key *expression* (or an invalid key) rather than one key.
_KEY_SPECIAL = set("*$?#")


def _check_convention(convention: str) -> None:
    if convention not in _CONVENTIONS:
        raise ValueError(f"unknown ROS 2 key convention {convention!r}; expected 'rmw_zenoh' or 'bridge'")


def _topic_path(topic: str) -> str:
    """``/robot1/chatter`` -> ``robot1/chatter``, refusing what no ROS 2 topic name is."""
    if not isinstance(topic, str):
        raise ValueError(f"topic {topic!r} is not a string")
    path = topic[1:] if topic.startswith("/") else topic
    chunks = path.split("/")
    if not path or not all(_NAME_CHUNK.fullmatch(c) for c in chunks):
        raise ValueError(
            f"{topic!r} is not a ROS 2 topic name (like /camera/color/image_raw: letters, digits, '_' between single '/')"
        )
    return path


def _prefix_path(prefix: str) -> str:
    """The bridge prefix as key chunks without outer slashes (``/robot1/`` -> ``robot1``)."""
    path = prefix.strip("/")
    if path and (any(not c for c in path.split("/")) or _KEY_SPECIAL & set(path) or any(c.isspace() for c in path)):
        raise ValueError(f"bridge prefix {prefix!r} is not a plain Zenoh key prefix (no wildcards, no empty chunks)")
    return path


def _check_domain(domain_id: int) -> int:
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise ValueError(f"ROS domain id {domain_id!r} is not a non-negative integer")
    return domain_id


def _key(convention: str, topic: str, domain_id: int, prefix: str, type_chunks: Callable[[], str]) -> str:
    """``topic``'s key: ``<domain_id>/<topic>/<type_chunks()>`` for rmw_zenoh, the topic under
    ``prefix/`` for the bridge (``type_chunks`` is only called for rmw_zenoh, whose keys name
    the type)."""
    _check_convention(convention)
    path = _topic_path(topic)
    if convention == "bridge":
        pre = _prefix_path(prefix)
        return f"{pre}/{path}" if pre else path
    return f"{_check_domain(domain_id)}/{path}/{type_chunks()}"


def data_key(
    convention: Convention, topic: str, ros_type: str, *, domain_id: int = 0, distro: str = "jazzy", prefix: str = ""
) -> str:
    """The Zenoh key a publisher of ``topic`` puts its samples on.

    rmw_zenoh: ``<domain_id>/<topic>/<dds type>/<RIHS01 hash of ros_type in distro>``
    (Humble: ``TypeHashNotSupported`` in place of the hash). bridge: the topic without its
    leading '/', under ``prefix/`` when ``prefix`` is set (``ros_type`` and ``distro`` unused).
    ``prefix`` belongs to the bridge only and is ignored for rmw_zenoh, whose keys have none.
    """
    return _key(convention, topic, domain_id, prefix, lambda: f"{dds_type_name(ros_type)}/{type_hash(ros_type, distro)}")


def subscribe_key(convention: Convention, topic: str, *, domain_id: int = 0, prefix: str = "") -> str:
    """A key expression that receives ``topic`` whatever type and hash its publishers use.

    rmw_zenoh: ``<domain_id>/<topic>/*/*`` (a sender on another distro, or on Humble, has
    another hash; the type is read back from each sample's key with :func:`parse_data_key`).
    bridge: the same key as :func:`data_key`.
    """
    return _key(convention, topic, domain_id, prefix, lambda: "*/*")


@dataclass(frozen=True)
class DataKey:
    """What a data key says: the topic (with its leading '/'), and under rmw_zenoh the ROS
    type, its type hash and the domain (None under the bridge convention)."""

    topic: str
    ros_type: str | None = None
    type_hash: str | None = None
    domain_id: int | None = None


def parse_data_key(convention: Convention, key: str, *, prefix: str = "") -> DataKey:
    """Read a sample's key back (inverse of :func:`data_key`); ValueError if it does not fit.

    rmw_zenoh keys are ``<domain>/<topic chunks...>/<dds type>/<hash>``: the topic may have
    any number of chunks, the last two are always the type and the hash. ``prefix`` is the
    bridge's and is ignored for rmw_zenoh.
    """
    _check_convention(convention)
    if not isinstance(key, str) or not key:
        raise ValueError(f"{key!r} is not a Zenoh key")
    if _KEY_SPECIAL & set(key):
        raise ValueError(f"{key!r} is a key expression with wildcards or reserved characters, not one sample's key")
    parts = key.split("/")
    if any(not p for p in parts):
        raise ValueError(f"{key!r} has an empty chunk (a leading, trailing or doubled '/')")
    if convention == "bridge":
        pre = _prefix_path(prefix)
        if pre:
            if not key.startswith(pre + "/"):
                raise ValueError(f"bridge key {key!r} is not under the prefix {pre!r}/")
            key = key[len(pre) + 1 :]
        return DataKey(topic="/" + key)
    if len(parts) < 4:
        raise ValueError(f"rmw_zenoh key {key!r} has {len(parts)} chunks; expected <domain_id>/<topic>/<dds type>/<type hash>")
    domain, *topic, dds, thash = parts
    if not domain.isdigit():
        raise ValueError(f"rmw_zenoh key {key!r} starts with {domain!r}, not a ROS domain id")
    if not (_RIHS01.fullmatch(thash) or thash == TYPE_HASH_NOT_SUPPORTED):
        raise ValueError(
            f"rmw_zenoh key {key!r} ends with {thash!r}, not a RIHS01_<64 hex> type hash or {TYPE_HASH_NOT_SUPPORTED}"
        )
    try:
        ros_type = ros_type_name(dds)
    except ValueError:
        raise ValueError(f"rmw_zenoh key {key!r}: {dds!r} is not a DDS type name like sensor_msgs::msg::dds_::Image_") from None
    return DataKey(topic="/" + "/".join(topic), ros_type=ros_type, type_hash=thash, domain_id=int(domain))


def _uleb128(n: int) -> bytes:
    """Unsigned LEB128, the length prefix zenoh's serializer writes before a byte sequence."""
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


@dataclass(frozen=True)
class Attachment:
    """The attachment rmw_zenoh puts on every publication (docs/design.md, "Publishers").

    Wire layout, as zenoh's serializer writes ``(int64, int64, uint8[16])``: sequence number
    (int64 little-endian), source timestamp in ns since the UNIX epoch (int64 LE), then the
    GID as a length-prefixed byte sequence (LEB128 length, always 16, so the single byte
    0x10, then 16 bytes): 33 bytes in all. zenoh-ros2-sdk writes the same bytes (it packs the
    length as one uint8, which LEB128 equals below 128).
    """

    sequence: int
    timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        for name in ("sequence", "timestamp_ns"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not _INT64[0] <= v <= _INT64[1]:
                raise ValueError(f"attachment {name} {v!r} is not an int64")
        if not isinstance(self.gid, (bytes, bytearray)) or len(self.gid) != GID_SIZE:
            raise ValueError(f"attachment gid must be {GID_SIZE} bytes, got {self.gid!r}")
        object.__setattr__(self, "gid", bytes(self.gid))

    def encode(self) -> bytes:
        """The 33 attachment bytes."""
        return struct.pack("<qq", self.sequence, self.timestamp_ns) + _uleb128(len(self.gid)) + self.gid

    @classmethod
    def decode(cls, b: bytes | bytearray | memoryview) -> Attachment:
        """Parse attachment bytes; ValueError if they are not exactly one rmw_zenoh attachment."""
        if not isinstance(b, (bytes, bytearray, memoryview)):
            raise ValueError(f"attachment must be bytes, got {type(b).__name__}")
        data = bytes(b)
        if len(data) < 17:
            raise ValueError(f"attachment of {len(data)} bytes is too short (sequence, timestamp and GID take {17 + GID_SIZE})")
        seq, stamp = struct.unpack_from("<qq", data)
        pos, length, shift = 16, 0, 0
        while True:
            if pos >= len(data) or shift > 28:  # a GID length needs one byte; 5 is already absurd
                raise ValueError("attachment GID length prefix is truncated or too long")
            byte = data[pos]
            pos += 1
            length |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
        if length != GID_SIZE:
            raise ValueError(f"attachment GID is {length} bytes; rmw_zenoh GIDs are {GID_SIZE}")
        if len(data) != pos + length:
            raise ValueError(f"attachment is {len(data)} bytes; a {GID_SIZE}-byte GID makes it {pos + length}")
        return cls(sequence=seq, timestamp_ns=stamp, gid=data[pos:])


def new_gid() -> bytes:
    """A fresh GID for one publisher: 16 random bytes (``os.urandom``).

    rmw_zenoh hashes each entity's liveliness key (xxh3-128) into its GID; receivers only use
    it as an opaque id of the sender (per-publisher sequence tracking, service replies), so
    random bytes, unique per endpoint, serve as well and need no hash implementation.
    """
    return os.urandom(GID_SIZE)


def mangle(name: str) -> str:
    """A name as one key chunk, as rmw_zenoh writes names into tokens: '/' -> '%', and the
    empty or root namespace (``""``, ``"/"``) becomes ``"%"``."""
    if not name or name == "/":
        return "%"
    return name.replace("/", "%")


def _demangle(chunk: str) -> str:
    """Inverse of :func:`mangle` for namespaces, enclaves and topic names (``%`` -> ``/``)."""
    return chunk.replace("%", "/")


def qos_string(*, reliable: bool = True, transient_local: bool = False, depth: int = 10) -> str:
    """An endpoint's QoS in rmw_zenoh's liveliness-token encoding (``qos_to_keyexpr``).

    Six ':'-separated fields: reliability, durability, ``<history>,<depth>``,
    ``<sec>,<nsec>`` of deadline and of lifespan, ``<kind>,<sec>,<nsec>`` of liveliness. A
    value equal to rmw_zenoh's default is left empty: reliable, volatile, keep-last, depth 42,
    infinite durations, automatic liveliness. Best effort is ``2``, transient local ``1``
    (rmw's enum values), so the default reliable, volatile, depth-10 endpoint is
    ``::,10:,:,:,,``. Depth 0 ("system default") is rmw_zenoh's 42.
    """
    if isinstance(depth, bool) or not isinstance(depth, int) or depth < 0:
        raise ValueError(f"QoS history depth {depth!r} is not a non-negative integer")
    rel = "" if reliable else "2"
    dur = "1" if transient_local else ""
    d = "" if depth in (0, RMW_ZENOH_DEFAULT_DEPTH) else str(depth)
    return f"{rel}:{dur}:,{d}:,:,:,,"


def _check_ids(session_id: str, **ids: int) -> None:
    if not isinstance(session_id, str) or not session_id or not all(c.isalnum() for c in session_id):
        raise ValueError(f"Zenoh session id {session_id!r} is not a hex string")
    for name, v in ids.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"{name} {v!r} is not a non-negative integer")


def _check_node(node_name: str, namespace: str, enclave: str) -> None:
    if not isinstance(node_name, str) or not _NODE_NAME.fullmatch(node_name):
        raise ValueError(f"{node_name!r} is not a ROS 2 node name (letters, digits and '_', not starting with a digit)")
    if namespace != "/":
        _topic_path(namespace)
        if not namespace.startswith("/"):
            raise ValueError(f"namespace {namespace!r} is not absolute (like /robot1)")
    if enclave not in ("%", "/"):
        _topic_path(enclave)


def node_token(domain_id: int, session_id: str, node_id: int, node_name: str, namespace: str = "/", enclave: str = "%") -> str:
    """The liveliness token of a node:
    ``@ros2_lv/<domain>/<session_id>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>``,
    names mangled (``enclave`` may be given mangled, ``%``, or plain, ``/``)."""
    _check_ids(session_id, node_id=node_id)
    _check_node(node_name, namespace, enclave)
    return (
        f"{ADMIN_SPACE}/{_check_domain(domain_id)}/{session_id}/{node_id}/{node_id}/NN/"
        f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node_name)}"
    )


def endpoint_token(
    kind: Literal["MP", "MS", "SS", "SC"],
    domain_id: int,
    session_id: str,
    node_id: int,
    entity_id: int,
    node_name: str,
    namespace: str,
    topic: str,
    ros_type: str,
    type_hash: str,
    qos: str,
    *,
    enclave: str = "%",
) -> str:
    """The liveliness token of a publisher (``MP``), subscription (``MS``), service server
    (``SS``) or client (``SC``) of node ``node_id``: the node token's chunks with
    ``entity_id`` in place of the second node id, then ``<mangled topic>/<dds type>/<type
    hash>/<qos>`` (``qos`` from :func:`qos_string`; ``topic`` fully qualified)."""
    if kind not in _ENDPOINT_KINDS:
        raise ValueError(f"endpoint kind {kind!r} is not one of {', '.join(_ENDPOINT_KINDS)}")
    _check_ids(session_id, node_id=node_id, entity_id=entity_id)
    _check_node(node_name, namespace, enclave)
    if not topic.startswith("/"):
        raise ValueError(f"topic {topic!r} is not fully qualified (tokens carry /<namespace>/<name>)")
    _topic_path(topic)
    if not (_RIHS01.fullmatch(type_hash) or type_hash == TYPE_HASH_NOT_SUPPORTED):
        raise ValueError(f"{type_hash!r} is not a RIHS01_<64 hex> type hash or {TYPE_HASH_NOT_SUPPORTED}")
    if not isinstance(qos, str) or qos.count(":") != 5 or "/" in qos or _KEY_SPECIAL & set(qos):
        raise ValueError(f"{qos!r} is not an rmw_zenoh QoS string (six ':'-separated fields, see qos_string)")
    return (
        f"{ADMIN_SPACE}/{_check_domain(domain_id)}/{session_id}/{node_id}/{entity_id}/{kind}/"
        f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node_name)}/{mangle(topic)}/{dds_type_name(ros_type)}/{type_hash}/{qos}"
    )


@dataclass(frozen=True)
class LivelinessEntity:
    """One ROS 2 graph entity read from its liveliness token (names demangled: namespace and
    enclave ``/`` when unset, topic fully qualified). For a node (``kind`` ``NN``),
    ``entity_id`` equals ``node_id`` and the topic fields are None."""

    domain_id: int
    session_id: str
    node_id: int
    entity_id: int
    kind: EntityKind
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: str | None = None


def parse_token(key: str) -> LivelinessEntity | None:
    """The entity a liveliness token announces, or None for a key that is not a well-formed
    rmw_zenoh node or endpoint token (other ``@ros2_lv`` keys, foreign liveliness tokens)."""
    parts = key.split("/") if isinstance(key, str) else []
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE:
        return None
    domain, zid, nid, eid, kind, enclave, ns, name = parts[1:9]
    is_node = len(parts) == 9
    if kind not in (("NN",) if is_node else _ENDPOINT_KINDS):
        log.debug("liveliness key %r: kind %r does not fit its %d chunks", key, kind, len(parts))
        return None
    if not (domain.isdigit() and nid.isdigit() and eid.isdigit()) or not all(parts):
        log.debug("liveliness key %r: ids are not numbers or a chunk is empty", key)
        return None
    entity = {
        "domain_id": int(domain), "session_id": zid, "node_id": int(nid), "entity_id": int(eid), "kind": kind,
        "enclave": _demangle(enclave), "namespace": _demangle(ns), "node_name": _demangle(name),
    }  # fmt: skip
    if is_node:
        return LivelinessEntity(**entity)
    topic, dds, thash, qos = parts[9:]
    try:
        ros_type = ros_type_name(dds)
    except ValueError:
        log.debug("liveliness key %r: %r is not a DDS type name", key, dds)
        return None
    return LivelinessEntity(**entity, topic=_demangle(topic), ros_type=ros_type, type_hash=thash, qos=qos)
