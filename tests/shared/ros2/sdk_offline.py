"""zenoh-ros2-sdk without the internet: message definitions from rosbags, a loopback session.

The SDK looks up ``.msg`` files in a messages folder and, for a type it does not find there,
clones the ROS 2 interface repositories from GitHub, which fails here. :func:`offline_sdk`
writes the definitions of the types a test needs (and everything they reference) from
rosbags' typestore into ``<tmp>/messages/<pkg>/msg/<Name>.msg``, installs a registry on that
folder as the SDK's global one, and disables the git path, so a missing type is a clear
FileNotFoundError instead of a clone. It also points the SDK's session at a loopback router
with multicast scouting off, and on exit closes the SDK's endpoints and its singleton session.

Usage (:func:`loopback_router` stands in for the robot's router)::

    port = free_port()
    with loopback_router(port) as router, offline_sdk(tmp_path, router_port=port) as sdk:
        pub = sdk.publisher("/camera/image_raw", "sensor_msgs/msg/Image")
        pub.publish(header=..., height=2, width=2, encoding="rgb8", is_bigendian=0, step=6, data=arr)
        sub = sdk.subscriber("/markers", "visualization_msgs/msg/MarkerArray", got.append)

Type hashes without any session: ``sdk.type_hash("sensor_msgs/msg/Image")``. The module also
builds sample messages (:func:`image`, :func:`camera_info`, :func:`tf_message`,
:func:`marker_array`) with rosbags' classes, which the SDK's publisher serialises as well.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.interfaces import Nodetype
from rosbags.typesys.msg import denormalize_msgtype

from shared.ros2.types import msg_class, typestore

TYPES = (
    "std_msgs/msg/String",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/msg/CameraInfo",
    "tf2_msgs/msg/TFMessage",
    "nav_msgs/msg/Odometry",
    "nav_msgs/msg/Path",
    "geometry_msgs/msg/PoseArray",
    "visualization_msgs/msg/MarkerArray",
)
"""The message types TrackGraph's ROS 2 tests exchange with the SDK."""

# rosbags' name for the member rosidl adds to an empty struct; a .msg file of such a type is
# empty (the SDK then adds the member back itself when it hashes the type).
_EMPTY_MEMBER = "structure_needs_at_least_one_member"


def _base(name: str, bound: int) -> str:
    return f"string<={bound}" if name == "string" and bound else name


def _field_line(name: str, desc: tuple[Any, Any]) -> tuple[str, list[str]]:
    """One ``.msg`` field line and the message types it references."""
    kind, arg = desc
    if kind == Nodetype.BASE:
        return f"{_base(*arg)} {name}", []
    if kind == Nodetype.NAME:
        return f"{denormalize_msgtype(arg)} {name}", [arg]
    (sub_kind, sub_arg), count = arg
    if kind == Nodetype.ARRAY:
        dims = f"[{count}]"
    else:
        dims = f"[<={count}]" if count else "[]"
    if sub_kind == Nodetype.BASE:
        return f"{_base(*sub_arg)}{dims} {name}", []
    return f"{denormalize_msgtype(sub_arg)}{dims} {name}", [sub_arg]


def _const_line(name: str, typ: str, value: Any) -> str:
    if isinstance(value, bool):
        value = "true" if value else "false"
    return f"{typ} {name}={value}"


def msg_text(ros_type: str, distro: str = "jazzy") -> tuple[str, list[str]]:
    """The ``.msg`` definition of ``ros_type`` as rosbags holds it (constants as
    ``type NAME=value``, fields as ``type name``, nested types as ``pkg/Name``), and the
    message types its fields reference."""
    consts, fields = typestore(distro).fielddefs[ros_type]
    lines = [_const_line(*c) for c in consts]
    refs: list[str] = []
    for name, desc in fields:
        if name == _EMPTY_MEMBER and len(fields) == 1:
            continue
        line, used = _field_line(name, desc)
        lines.append(line)
        refs += [r for r in used if r not in refs]
    return "".join(f"{line}\n" for line in lines), refs


def write_messages(root: Path, types: Iterable[str] = TYPES, distro: str = "jazzy") -> dict[str, Path]:
    """Write ``root/<pkg>/msg/<Name>.msg`` for ``types`` and every type they reference,
    recursively; returns the files written by type name."""
    written: dict[str, Path] = {}
    todo = list(types)
    while todo:
        name = todo.pop()
        if name in written:
            continue
        pkg, kind, short = name.split("/")
        if kind != "msg":
            raise ValueError(f"{name}: only message types can be written (services are not needed offline)")
        text, refs = msg_text(name, distro)
        path = root / pkg / "msg" / f"{short}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written[name] = path
        todo += refs
    return written


# --- sample messages (rosbags classes of shared.ros2.types; the SDK serialises them too) ---

_T = {name: msg_class(name) for name in (
    "builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration", "std_msgs/msg/Header", "std_msgs/msg/ColorRGBA",
    "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/RegionOfInterest",
    "geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Pose", "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Transform", "geometry_msgs/msg/TransformStamped", "tf2_msgs/msg/TFMessage",
    "visualization_msgs/msg/Marker", "visualization_msgs/msg/MarkerArray", "visualization_msgs/msg/MeshFile",
)}  # fmt: skip


def header(stamp_ns: int, frame: str):
    """A std_msgs/Header at ``stamp_ns``."""
    stamp = _T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return _T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def image(rng: np.random.Generator, h: int = 3, w: int = 4):
    """An rgb8 sensor_msgs/Image of random pixels, stamped 1700000000.123456789."""
    data = rng.integers(0, 256, size=h * w * 3, dtype=np.uint8)
    return _T["sensor_msgs/msg/Image"](header=header(1_700_000_000_123_456_789, "cam"), height=h, width=w,
                                      encoding="rgb8", is_bigendian=0, step=w * 3, data=data)  # fmt: skip


def camera_info():
    """A 640x480 plumb_bob sensor_msgs/CameraInfo (f = 500 px)."""
    k = np.array([500.0, 0, 320, 0, 500, 240, 0, 0, 1])
    p = np.array([500.0, 0, 320, 0, 0, 500, 240, 0, 0, 0, 1, 0])
    roi = _T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return _T["sensor_msgs/msg/CameraInfo"](
        header=header(5, "cam"), height=480, width=640, distortion_model="plumb_bob", d=np.zeros(5), k=k,
        r=np.eye(3).reshape(-1), p=p, binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def tf_message():
    """A tf2_msgs/TFMessage of three transforms under ``map``."""
    tfs = []
    for i, child in enumerate(("odom", "base_link", "camera_link")):
        shift = _T["geometry_msgs/msg/Vector3"](x=i, y=-0.5 * i, z=0.1)
        turn = _T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0.3826834, w=0.9238795)
        tr = _T["geometry_msgs/msg/Transform"](translation=shift, rotation=turn)
        tfs.append(_T["geometry_msgs/msg/TransformStamped"](header=header(10 + i, "map"), child_frame_id=child, transform=tr))
    return _T["tf2_msgs/msg/TFMessage"](transforms=tfs)


def marker(i: int, kind: int, text: str = "", points: int = 0):
    """A visualization_msgs/Marker ``i`` of ``kind`` in ``map`` (``points`` points and colours)."""
    P, C = _T["geometry_msgs/msg/Point"], _T["std_msgs/msg/ColorRGBA"]
    upright = _T["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1)
    pose = _T["geometry_msgs/msg/Pose"](position=P(x=i, y=2.0 * i, z=0.5), orientation=upright)
    texture = _T["sensor_msgs/msg/CompressedImage"](header=header(0, ""), format="", data=np.zeros(0, np.uint8))
    mesh = _T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8))
    return _T["visualization_msgs/msg/Marker"](
        header=header(42 + i, "map"), ns="segments", id=i, type=kind, action=0, pose=pose,
        scale=_T["geometry_msgs/msg/Vector3"](x=0.1, y=0.2, z=0.3), color=C(r=1.0, g=0.5, b=0.25, a=0.8),
        lifetime=_T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False,
        points=[P(x=j, y=-j, z=0.25 * j) for j in range(points)], colors=[C(r=0, g=1, b=0, a=1)] * points,
        texture_resource="", texture=texture, uv_coordinates=[], text=text, mesh_resource="", mesh_file=mesh,
        mesh_use_embedded_materials=False,
    )  # fmt: skip


def marker_array():
    """A MarkerArray of a cube, a text and a line list (ids 0, 1, 2)."""
    M = _T["visualization_msgs/msg/Marker"]
    return _T["visualization_msgs/msg/MarkerArray"](
        markers=[marker(0, M.CUBE), marker(1, M.TEXT_VIEW_FACING, text="armchair #1"), marker(2, M.LINE_LIST, points=4)]
    )


# --- the SDK, offline and on the loopback ---------------------------------------------------


def _refuse_git(*args: Any, **kwargs: Any) -> Any:
    raise RuntimeError("zenoh-ros2-sdk tried to clone a message repository; offline tests have all definitions on disk")


class OfflineSdk:
    """zenoh-ros2-sdk set up for one test (see the module docstring); a context manager."""

    def __init__(self, tmp_dir: Path, distro: str = "jazzy", types: Iterable[str] = TYPES, *,
                 router_port: int | None = None, domain_id: int = 0) -> None:  # fmt: skip
        self.root = Path(tmp_dir)
        self.messages_dir = self.root / "messages"
        self.files = write_messages(self.messages_dir, types, distro)
        self.router_port = router_port
        self.domain_id = domain_id
        self._endpoints: list[Any] = []
        self._saved_env: dict[str, str | None] = {}
        self._saved_attrs: list[tuple[Any, str, Any]] = []
        self.registry: Any = None

    def _patch(self, obj: Any, name: str, value: Any) -> None:
        self._saved_attrs.append((obj, name, getattr(obj, name)))
        setattr(obj, name, value)

    def _setenv(self, name: str, value: str | None) -> None:
        self._saved_env.setdefault(name, os.environ.get(name))
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value

    def __enter__(self) -> OfflineSdk:
        from zenoh_ros2_sdk import _cache, message_registry
        from zenoh_ros2_sdk.session import ZenohSession

        if ZenohSession._instance is not None:
            raise RuntimeError("a zenoh-ros2-sdk session is already open; an earlier test did not close it")
        # The registry is module-global: get_registry() returns it to publishers, subscribers
        # and the session; a fresh one per test also forgets types loaded into a closed session.
        self.registry = message_registry.MessageRegistry(str(self.messages_dir))
        self._patch(message_registry, "_registry", self.registry)
        # A type missing from the folder must not send the SDK to GitHub: no package maps to
        # a repository, and the clone functions refuse.
        self._patch(message_registry, "get_repository_for_package", lambda package: None)
        self._patch(message_registry, "clone_to_cache", _refuse_git)
        self._patch(message_registry, "get_message_file_path", _refuse_git)
        self._patch(_cache, "clone_to_cache", _refuse_git)
        self._setenv("ZENOH_ROS2_SDK_CACHE", str(self.root / "sdk_cache"))
        # The bundled session config (rmw_zenoh's default: peer, multicast scouting disabled)
        # rather than whatever file the environment names; the override pins what matters to
        # a test: no multicast, and listening on the loopback only.
        self._setenv("ZENOH_SESSION_CONFIG_URI", None)
        self._setenv("ZENOH_CONFIG_OVERRIDE", 'scouting/multicast/enabled=false;listen/endpoints=["tcp/127.0.0.1:0"]')
        self._setenv("ROS_DOMAIN_ID", None)
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close every endpoint made through :meth:`publisher`/:meth:`subscriber`, then the
        SDK's singleton session (and reset it), then undo the patches and env changes."""
        from zenoh_ros2_sdk.session import ZenohSession

        try:
            for ep in reversed(self._endpoints):
                ep.close()
            self._endpoints.clear()
            inst = ZenohSession._instance
            if inst is not None:
                inst.close()  # closes the zenoh session and clears the singleton
                ZenohSession._instance = None
        finally:
            for obj, name, value in reversed(self._saved_attrs):
                setattr(obj, name, value)
            self._saved_attrs.clear()
            for name, value in self._saved_env.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
            self._saved_env.clear()

    def _router(self) -> dict[str, Any]:
        if self.router_port is None:
            raise RuntimeError("offline_sdk(..., router_port=PORT) is needed for endpoints")
        return {"router_ip": "127.0.0.1", "router_port": self.router_port, "domain_id": self.domain_id}

    def publisher(self, topic: str, ros_type: str, **kwargs: Any) -> Any:
        """A ``ROS2Publisher`` on the loopback router, closed with the SDK."""
        from zenoh_ros2_sdk import ROS2Publisher

        pub = ROS2Publisher(topic, ros_type, **{**self._router(), **kwargs})
        self._endpoints.append(pub)
        return pub

    def subscriber(self, topic: str, ros_type: str, callback: Callable[[Any], None], **kwargs: Any) -> Any:
        """A ``ROS2Subscriber`` on the loopback router, closed with the SDK."""
        from zenoh_ros2_sdk import ROS2Subscriber

        sub = ROS2Subscriber(topic, ros_type, callback, **{**self._router(), **kwargs})
        self._endpoints.append(sub)
        return sub

    def type_hash(self, ros_type: str) -> str:
        """The RIHS01 hash the SDK computes for ``ros_type`` from the written definitions,
        exactly as its publisher does (no session needed)."""
        from zenoh_ros2_sdk.utils import get_type_hash, load_dependencies_recursive

        path = self.registry.get_msg_file_path(ros_type)
        if path is None:
            raise FileNotFoundError(f"{ros_type}: no definition in {self.messages_dir}")
        text = path.read_text()
        deps = load_dependencies_recursive(ros_type, text, self.registry)
        return get_type_hash(ros_type, msg_definition=text, dependencies=deps)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def loopback_router(port: int) -> Iterator[Any]:
    """A Zenoh session in router mode on ``tcp/127.0.0.1:<port>``, multicast scouting off,
    connecting nowhere: the robot's ``rmw_zenohd`` in a test. Closed on exit."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        yield session
    finally:
        session.close()


def offline_sdk(tmp_dir: Path, distro: str = "jazzy", types: Iterable[str] = TYPES, *,
                router_port: int | None = None, domain_id: int = 0) -> OfflineSdk:  # fmt: skip
    """zenoh-ros2-sdk with ``types`` on disk under ``tmp_dir`` and its session aimed at
    ``tcp/127.0.0.1:<router_port>``; use as ``with offline_sdk(tmp_path, router_port=p) as sdk``."""
    return OfflineSdk(tmp_dir, distro, types, router_port=router_port, domain_id=domain_id)
