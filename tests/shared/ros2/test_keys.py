"""shared.ros2.keys: data keys of both conventions, the rmw_zenoh attachment and liveliness
tokens, checked against rmw_zenoh's documented examples and against zenoh-ros2-sdk."""

from __future__ import annotations

import struct
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import zenoh
from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
from zenoh_ros2_sdk.keyexpr import (
    endpoint_liveliness_keyexpr,
    node_liveliness_keyexpr,
    topic_keyexpr,
)
from zenoh_ros2_sdk.publisher import ROS2Publisher
from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability
from zenoh_ros2_sdk.utils import mangle_name

sys.path.insert(0, str(Path(__file__).parent))  # sdk_offline by bare name, under any import mode

from sdk_offline import free_port, loopback_router, marker_array, offline_sdk  # noqa: E402

from shared.ros2 import keys  # noqa: E402
from shared.ros2.types import dds_type_name, decode, encode, msg_class, type_hash  # noqa: E402

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
ZID = "aac3178e146ba6f1fc6e6a4085e77f21"
GID = bytes(range(16))


# --- data keys ---------------------------------------------------------------------------


def test_rmw_zenoh_data_keys_match_the_design_doc():
    # The examples of rmw_zenoh's docs/design.md ("Topic and Service name mapping").
    string = f"std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert keys.data_key("rmw_zenoh", "/chatter", "std_msgs/msg/String") == f"0/chatter/{string}"
    assert keys.data_key("rmw_zenoh", "/robot1/chatter", "std_msgs/msg/String") == f"0/robot1/chatter/{string}"
    assert keys.data_key("rmw_zenoh", "chatter", "std_msgs/msg/String", domain_id=7).startswith("7/chatter/")


def test_rmw_zenoh_data_key_equals_the_sdks():
    for topic, ros_type in [("/camera/color/image_raw", "sensor_msgs/msg/Image"), ("/tf", "tf2_msgs/msg/TFMessage")]:
        sdk = topic_keyexpr(3, topic, dds_type_name(ros_type), type_hash(ros_type))
        assert keys.data_key("rmw_zenoh", topic, ros_type, domain_id=3) == sdk


def test_humble_keys_carry_no_hash():
    key = keys.data_key("rmw_zenoh", "/tf", "tf2_msgs/msg/TFMessage", distro="humble")
    assert key == "0/tf/tf2_msgs::msg::dds_::TFMessage_/TypeHashNotSupported"
    assert keys.parse_data_key("rmw_zenoh", key).type_hash == "TypeHashNotSupported"


def test_bridge_keys_are_the_topic_under_the_prefix():
    assert keys.data_key("bridge", "/camera/color/image_raw", "sensor_msgs/msg/Image") == "camera/color/image_raw"
    for prefix in ("robot1", "/robot1/", "fleet/robot1"):
        key = keys.data_key("bridge", "/tf", "tf2_msgs/msg/TFMessage", prefix=prefix)
        assert key == f"{prefix.strip('/')}/tf"
        assert keys.subscribe_key("bridge", "/tf", prefix=prefix) == key
        assert keys.parse_data_key("bridge", key, prefix=prefix) == keys.DataKey(topic="/tf")
    # the prefix is the bridge's: an rmw_zenoh key has none
    assert keys.data_key("rmw_zenoh", "/tf", "tf2_msgs/msg/TFMessage", prefix="robot1").startswith("0/tf/")


@pytest.mark.parametrize("topic", ["/chatter", "/robot1/chatter", "/camera/aligned_depth_to_color/image_raw"])
def test_subscribe_key_receives_any_type_and_hash_of_exactly_that_topic(topic):
    sub = zenoh.KeyExpr(keys.subscribe_key("rmw_zenoh", topic, domain_id=4))
    for ros_type, distro in [("sensor_msgs/msg/Image", "jazzy"), ("sensor_msgs/msg/CompressedImage", "humble")]:
        assert sub.intersects(zenoh.KeyExpr(keys.data_key("rmw_zenoh", topic, ros_type, domain_id=4, distro=distro)))
    others = [keys.data_key("rmw_zenoh", topic + "/sub", "sensor_msgs/msg/Image", domain_id=4),
              keys.data_key("rmw_zenoh", topic, "sensor_msgs/msg/Image", domain_id=5)]  # fmt: skip
    if topic.count("/") > 1:
        others.append(keys.data_key("rmw_zenoh", topic.rsplit("/", 1)[0], "sensor_msgs/msg/Image", domain_id=4))
    for other in others:
        assert not sub.intersects(zenoh.KeyExpr(other)), other


@pytest.mark.parametrize("topic", ["/chatter", "/a/b/c/d/e", "/robot1/camera/color/image_raw"])
def test_rmw_zenoh_keys_parse_back(topic):
    for ros_type in ("sensor_msgs/msg/Image", "visualization_msgs/msg/MarkerArray"):
        key = keys.data_key("rmw_zenoh", topic, ros_type, domain_id=12)
        assert keys.parse_data_key("rmw_zenoh", key) == keys.DataKey(topic, ros_type, type_hash(ros_type), 12)


@pytest.mark.parametrize(
    ("key", "why"),
    [
        ("", "not a Zenoh key"),
        ("0/chatter/std_msgs::msg::dds_::String_", "3 chunks"),
        (f"x/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}", "not a ROS domain id"),
        ("0/chatter/std_msgs::msg::dds_::String_/RIHS01_1234", "type hash"),
        (f"0/chatter/std_msgs/msg/String/{STRING_HASH}", "DDS type name"),
        (f"0/chatter/String/{STRING_HASH}", "DDS type name"),
        (f"0/chatter/*/{STRING_HASH}", "wildcards"),
        (f"0//chatter/std_msgs::msg::dds_::String_/{STRING_HASH}", "empty chunk"),
        (f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/", "empty chunk"),
    ],
)
def test_malformed_rmw_zenoh_keys_are_refused(key, why):
    with pytest.raises(ValueError, match=why):
        keys.parse_data_key("rmw_zenoh", key)


def test_bridge_key_outside_the_prefix_is_refused():
    with pytest.raises(ValueError, match="not under the prefix"):
        keys.parse_data_key("bridge", "robot2/tf", prefix="robot1")
    with pytest.raises(ValueError, match="not under the prefix"):
        keys.parse_data_key("bridge", "robot1", prefix="robot1")
    assert keys.parse_data_key("bridge", "robot1/camera/image_raw").topic == "/robot1/camera/image_raw"


@pytest.mark.parametrize("topic", ["", "/", "//chatter", "/chatter/", "/cha tter", "/camera/*", "/a/**", "/a#b"])
def test_bad_topics_are_refused_by_name(topic):
    for call in (lambda: keys.data_key("rmw_zenoh", topic, "std_msgs/msg/String"),
                 lambda: keys.data_key("bridge", topic, "std_msgs/msg/String"),
                 lambda: keys.subscribe_key("rmw_zenoh", topic)):  # fmt: skip
        with pytest.raises(ValueError, match="not a ROS 2 topic name"):
            call()


def test_bad_convention_domain_and_prefix_are_refused():
    with pytest.raises(ValueError, match="unknown ROS 2 key convention"):
        keys.data_key("dds", "/tf", "tf2_msgs/msg/TFMessage")
    with pytest.raises(ValueError, match="domain id"):
        keys.subscribe_key("rmw_zenoh", "/tf", domain_id=-1)
    with pytest.raises(ValueError, match="bridge prefix"):
        keys.subscribe_key("bridge", "/tf", prefix="robots/*")


# --- attachments -------------------------------------------------------------------------


def test_attachment_layout_and_round_trip():
    att = keys.Attachment(sequence=7, timestamp_ns=1_700_000_000_123_456_789, gid=GID)
    b = att.encode()
    assert len(b) == 33
    assert b == struct.pack("<qq", 7, 1_700_000_000_123_456_789) + b"\x10" + GID
    assert keys.Attachment.decode(b) == att
    assert keys.Attachment.decode(bytearray(b)) == att and keys.Attachment.decode(memoryview(b)) == att
    # rmw_zenoh's fields are int64: negative values survive
    neg = keys.Attachment(sequence=-1, timestamp_ns=-(2**63), gid=GID)
    assert keys.Attachment.decode(neg.encode()) == neg


def test_attachment_is_byte_compatible_with_the_sdk():
    for seq, stamp, gid in [(0, 0, GID), (1, 1_700_000_000_000_000_000, keys.new_gid()), (2**63 - 1, 2**63 - 1, b"\xff" * 16)]:
        ours = keys.Attachment(sequence=seq, timestamp_ns=stamp, gid=gid)
        theirs = SdkAttachment(sequence_id=seq, timestamp_ns=stamp, gid=gid)
        assert ours.encode() == theirs.to_bytes()
        assert keys.Attachment.decode(theirs.to_bytes()) == ours
        assert SdkAttachment.from_bytes(ours.encode()) == theirs
        # what the SDK's publisher actually puts on the wire
        wire = ROS2Publisher._create_attachment(SimpleNamespace(publisher_gid=gid), seq, stamp)
        assert keys.Attachment.decode(wire) == ours


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        (b"", "too short"),
        (b"\x00" * 16, "too short"),
        (struct.pack("<qq", 1, 2) + b"\x10" + GID[:15], "is 32 bytes"),
        (struct.pack("<qq", 1, 2) + b"\x10" + GID + b"\x00", "is 34 bytes"),
        (struct.pack("<qq", 1, 2) + b"\x0f" + GID[:15], "GID is 15 bytes"),
        (struct.pack("<qq", 1, 2) + b"\x18" + bytes(24), "GID is 24 bytes"),
        (struct.pack("<qq", 1, 2) + b"\x80" * 8, "length prefix"),
        (struct.pack("<qq", 1, 2) + b"\x90", "length prefix"),
        (None, "must be bytes"),
        ("0123456789abcdef0123456789abcdef0", "must be bytes"),
    ],
)
def test_malformed_attachments_raise_value_error(payload, why):
    with pytest.raises(ValueError, match=why):
        keys.Attachment.decode(payload)


def test_attachment_fields_are_checked():
    with pytest.raises(ValueError, match="gid must be 16 bytes"):
        keys.Attachment(sequence=1, timestamp_ns=0, gid=b"short")
    with pytest.raises(ValueError, match="sequence"):
        keys.Attachment(sequence=2**63, timestamp_ns=0, gid=GID)
    with pytest.raises(ValueError, match="timestamp_ns"):
        keys.Attachment(sequence=0, timestamp_ns=1.5, gid=GID)


def test_new_gid_is_sixteen_fresh_bytes():
    gids = {keys.new_gid() for _ in range(64)}
    assert len(gids) == 64 and all(len(g) == 16 for g in gids)


# --- liveliness tokens -------------------------------------------------------------------


def test_mangle_matches_rmw_zenoh_and_the_sdk():
    cases = [("/", "%"), ("", "%"), ("/robot1", "%robot1"), ("talker", "talker"),
             ("/robot1/camera/image_raw", "%robot1%camera%image_raw")]  # fmt: skip
    for name, mangled in cases:
        assert keys.mangle(name) == mangled == mangle_name(name)


def test_qos_strings_match_the_design_doc_and_the_sdk():
    assert keys.qos_string() == "::,10:,:,:,,"  # the listener's subscription in design.md
    assert keys.qos_string(depth=7) == "::,7:,:,:,,"  # the talker's publisher
    for reliable in (True, False):
        for transient_local in (False, True):
            for depth in (1, 5, 10, 100):
                sdk = QosProfile(
                    reliability=QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
                    durability=QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
                    history_depth=depth,
                ).encode()
                assert keys.qos_string(reliable=reliable, transient_local=transient_local, depth=depth) == sdk
    assert keys.qos_string(reliable=False, transient_local=True, depth=1) == "2:1:,1:,:,:,,"
    # rmw_zenoh leaves its own default depth, 42, out (the SDK writes it; rmw_zenoh reads both)
    assert keys.qos_string(depth=42) == keys.qos_string(depth=0) == "::,:,:,:,,"
    with pytest.raises(ValueError, match="depth"):
        keys.qos_string(depth=-1)


def test_tokens_match_the_design_doc():
    # docs/design.md, "Graph Cache": demo_nodes_cpp's listener and talker on domain 2.
    assert keys.node_token(2, ZID, 0, "listener") == f"@ros2_lv/2/{ZID}/0/0/NN/%/%/listener"
    string = ("/chatter", "std_msgs/msg/String", STRING_HASH)
    ms = keys.endpoint_token("MS", 2, ZID, 0, 10, "listener", "/", *string, keys.qos_string())
    assert ms == f"@ros2_lv/2/{ZID}/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
    talker = "8b20917502ee955ac4476e0266340d5c"
    mp = keys.endpoint_token("MP", 2, talker, 0, 10, "talker", "/", *string, keys.qos_string(depth=7))
    assert mp == f"@ros2_lv/2/{talker}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
    ss = keys.endpoint_token("SS", 2, ZID, 0, 10, "add_two_ints_server", "/", "/add_two_ints",
                             "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH, keys.qos_string())  # fmt: skip
    assert ss == (f"@ros2_lv/2/{ZID}/0/10/SS/%/%/add_two_ints_server/%add_two_ints/"
                  f"example_interfaces::srv::dds_::AddTwoInts_/{ADD_TWO_INTS_HASH}/::,10:,:,:,,")  # fmt: skip


ENTITIES = [
    # kind, domain, node_id, entity_id, node, namespace, topic, ros_type, qos kwargs
    ("MP", 0, 1, 2, "trackgraph", "/", "/trackgraph/scene_graph", "visualization_msgs/msg/MarkerArray",
     {"transient_local": True, "depth": 1}),
    ("MS", 0, 1, 3, "trackgraph", "/", "/camera/color/image_raw", "sensor_msgs/msg/Image", {"reliable": False, "depth": 5}),
    ("MS", 17, 4, 9, "mapper_2", "/robot1", "/robot1/tf_static", "tf2_msgs/msg/TFMessage", {"transient_local": True}),
    ("MP", 232, 0, 1, "nav", "/fleet/robot1", "/fleet/robot1/odom", "nav_msgs/msg/Odometry", {}),
]
SDK_KIND = {"MP": EntityKind.PUBLISHER, "MS": EntityKind.SUBSCRIPTION, "SS": EntityKind.SERVICE, "SC": EntityKind.CLIENT}


@pytest.mark.parametrize("entity", ENTITIES, ids=[e[6] for e in ENTITIES])
def test_tokens_equal_the_sdks_and_parse_back(entity):
    kind, domain, node_id, entity_id, node_name, namespace, topic, ros_type, qos_kw = entity
    qos = keys.qos_string(**qos_kw)
    thash = type_hash(ros_type)
    node = NodeEntity(domain_id=domain, session_id=ZID, node_id=node_id, node_name=node_name, namespace=namespace)
    ep = EndpointEntity(node=node, entity_id=entity_id, kind=SDK_KIND[kind], name=topic, dds_type_name=dds_type_name(ros_type),
                        type_hash=thash, qos=qos, gid=GID)  # fmt: skip
    nn = keys.node_token(domain, ZID, node_id, node_name, namespace)
    token = keys.endpoint_token(kind, domain, ZID, node_id, entity_id, node_name, namespace, topic, ros_type, thash, qos)
    assert nn == node_liveliness_keyexpr(node)
    assert token == endpoint_liveliness_keyexpr(ep)

    parsed = keys.parse_token(token)
    assert parsed == keys.LivelinessEntity(
        domain, ZID, node_id, entity_id, kind, "/", namespace, node_name, topic, ros_type, thash, qos
    )  # fmt: skip
    p = parsed
    rebuilt = keys.endpoint_token(p.kind, p.domain_id, p.session_id, p.node_id, p.entity_id, p.node_name, p.namespace,
                                  p.topic, p.ros_type, p.type_hash, p.qos, enclave=p.enclave)  # fmt: skip
    assert rebuilt == token
    pn = keys.parse_token(nn)
    assert pn == keys.LivelinessEntity(domain, ZID, node_id, node_id, "NN", "/", namespace, node_name)
    assert keys.node_token(pn.domain_id, pn.session_id, pn.node_id, pn.node_name, pn.namespace, pn.enclave) == nn


@pytest.mark.parametrize(
    "key",
    [
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}",
        "@ros2_lv/0/abc",
        f"@ros2_lv/0/{ZID}/0/0/XX/%/%/listener",
        f"@ros2_lv/0/{ZID}/0/0/MP/%/%/listener",  # an endpoint kind on a node token
        f"@ros2_lv/0/{ZID}/0/10/NN/%/%/listener/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,",
        f"@ros2_lv/x/{ZID}/0/0/NN/%/%/listener",
        f"@ros2_lv/0/{ZID}/a/0/NN/%/%/listener",
        f"@ros2_lv/0/{ZID}/0/10/MS/%/%/listener/%chatter/std_msgs/msg/String/{STRING_HASH}/::,10:,:,:,,",
        f"@ros2_lv/0/{ZID}/0/10/MS/%/%/listener/%chatter//{STRING_HASH}/::,10:,:,:,,",
        f"@other/0/{ZID}/0/0/NN/%/%/listener",
        None,
    ],
)
def test_parse_token_ignores_what_is_not_a_ros_token(key):
    assert keys.parse_token(key) is None


def test_token_arguments_are_checked():
    tf = "tf2_msgs/msg/TFMessage"
    args = ("MP", 0, ZID, 1, 2, "trackgraph", "/", "/tf", tf, type_hash(tf), keys.qos_string())
    assert keys.endpoint_token(*args).startswith("@ros2_lv/0/")
    bad = {
        0: ("NN", "endpoint kind"), 2: ("not/hex", "session id"), 4: (-1, "entity_id"), 5: ("2fast", "node name"),
        6: ("robot1", "not absolute"), 7: ("tf", "fully qualified"), 9: ("RIHS01_xyz", "type hash"), 10: ("::,10", "QoS string"),
    }  # fmt: skip
    for i, (value, why) in bad.items():
        with pytest.raises(ValueError, match=why):
            keys.endpoint_token(*args[:i], value, *args[i + 1 :])
    with pytest.raises(ValueError, match="node_id"):
        keys.node_token(0, ZID, -3, "trackgraph")


# --- on the wire, with the SDK on a loopback router --------------------------------------


def _wait(cond, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.02)
    return cond()


@pytest.mark.zenoh
def test_sdk_endpoints_and_ours_understand_each_other(tmp_path):
    """An SDK publisher's Image arrives on keys.subscribe_key with our key, attachment and
    tokens; a MarkerArray put on keys.data_key with our attachment reaches an SDK subscriber."""
    port = free_port()
    with loopback_router(port) as router, offline_sdk(tmp_path, router_port=port) as sdk:
        samples, tokens, markers = [], [], []

        def on_image(s):
            samples.append((str(s.key_expr), s.payload.to_bytes(), s.attachment.to_bytes()))

        router.declare_subscriber(keys.subscribe_key("rmw_zenoh", "/camera/image_raw"), on_image)
        router.liveliness().declare_subscriber(f"{keys.ADMIN_SPACE}/0/**", lambda s: tokens.append(str(s.key_expr)), history=True)

        pub = sdk.publisher("/camera/image_raw", "sensor_msgs/msg/Image", node_name="camera", namespace="/robot1")
        H, Tm = msg_class("std_msgs/msg/Header"), msg_class("builtin_interfaces/msg/Time")
        data = np.arange(12, dtype=np.uint8)

        def publish():
            pub.publish(header=H(stamp=Tm(sec=3, nanosec=4), frame_id="cam"), height=2, width=2, encoding="rgb8",
                        is_bigendian=0, step=6, data=data)  # fmt: skip
            return bool(samples)

        assert _wait(publish), "no Image from the SDK publisher"
        key, payload, attachment = samples[0]
        assert key == keys.data_key("rmw_zenoh", "/camera/image_raw", "sensor_msgs/msg/Image")
        assert keys.parse_data_key("rmw_zenoh", key).ros_type == "sensor_msgs/msg/Image"
        att = keys.Attachment.decode(attachment)
        assert att.gid == pub.publisher_gid and att.timestamp_ns > 1_600_000_000 * 10**9
        np.testing.assert_array_equal(decode(payload, "sensor_msgs/msg/Image").data, data)

        assert _wait(lambda: len(tokens) >= 2)
        entities = {e.kind: e for e in map(keys.parse_token, tokens) if e is not None}
        assert entities["NN"].node_name == "camera" and entities["NN"].namespace == "/robot1"
        mp = entities["MP"]
        expected = ("/camera/image_raw", "sensor_msgs/msg/Image", type_hash("sensor_msgs/msg/Image"), keys.qos_string())
        assert (mp.topic, mp.ros_type, mp.type_hash, mp.qos) == expected
        assert mp.session_id == entities["NN"].session_id == str(sdk.registry.session.session_id)

        sdk.subscriber("/trackgraph/scene_graph", "visualization_msgs/msg/MarkerArray", markers.append)
        out_key = keys.data_key("rmw_zenoh", "/trackgraph/scene_graph", "visualization_msgs/msg/MarkerArray")
        msg = marker_array()
        gid = keys.new_gid()

        def put():
            att = keys.Attachment(sequence=1, timestamp_ns=time.time_ns(), gid=gid)
            router.put(out_key, encode(msg), attachment=att.encode())
            return bool(markers)

        assert _wait(put), "the SDK subscriber got nothing on our key"
        got = markers[0]
        assert [m.id for m in got.markers] == [0, 1, 2] and got.markers[1].text == "armchair #1"
        assert [(p.x, p.y) for p in got.markers[2].points] == [(j, -j) for j in range(4)]
