"""The rmw_zenoh wire helpers against the literal examples of rmw_zenoh's design document."""

from __future__ import annotations

import struct
import sys

import numpy as np
import pytest
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io import ros2_wire as w

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
"""std_msgs/msg/String's hash in rmw_zenoh's docs/design.md examples."""
LASER_SCAN_KEY = (
    "0/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
)
"""The key zenoh-ros2-sdk's LaserScan publisher was seen using on a router (Jazzy definitions)."""


def test_type_hashes_are_the_ones_on_the_wire():
    assert w.type_hash("std_msgs/msg/String") == STRING_HASH
    # rosbags' own test value (REP-2011)
    assert w.type_hash("std_msgs/msg/Byte").startswith("RIHS01_41e1a334") and w.type_hash("std_msgs/msg/Byte").endswith(
        "798f"
    )
    with pytest.raises(BadInput, match="not a message type"):
        w.type_hash("nope_msgs/msg/Nothing")


def test_data_keys_are_the_design_documents():
    assert w.data_key(0, "/chatter", "std_msgs/msg/String") == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert (
        w.data_key(0, w.fully_qualified("/robot1", "chatter"), "std_msgs/msg/String")
        == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert w.data_key(0, "/scan", w.LASER_SCAN) == LASER_SCAN_KEY
    assert w.data_key(3, "/robot1/odom", w.ODOMETRY, w.ANY_HASH) == "3/robot1/odom/nav_msgs::msg::dds_::Odometry_/*"
    with pytest.raises(BadInput, match="domain"):
        w.data_key(-1, "/scan", w.LASER_SCAN)


@pytest.mark.parametrize(
    ("namespace", "topic", "name"),
    [("", "scan", "/scan"), ("/", "scan", "/scan"), ("/robot1", "scan", "/robot1/scan"), ("robot1/", "/tf", "/tf")],
)
def test_topic_names_are_qualified_by_the_namespace_unless_absolute(namespace, topic, name):
    assert w.fully_qualified(namespace, topic) == name


def test_cdr_payloads_carry_the_little_endian_header_and_round_trip():
    T = w.typestore().types
    stamp = T["builtin_interfaces/msg/Time"](sec=12, nanosec=500)
    scan = T[w.LASER_SCAN](
        T["std_msgs/msg/Header"](stamp, "laser"),
        -1.0, 1.0, 0.5, 0.0, 0.1, 0.05, 8.0,
        np.array([1.0, 2.0, np.inf, 3.0, 4.0], dtype=np.float32),
        np.zeros(0, dtype=np.float32),
    )  # fmt: skip
    payload = w.encode(scan, w.LASER_SCAN)
    assert payload[:4] == w.ENCAPSULATION == b"\x00\x01\x00\x00"
    back = w.decode(payload, w.LASER_SCAN)
    assert back.header.frame_id == "laser" and back.header.stamp.sec == 12
    np.testing.assert_array_equal(back.ranges, scan.ranges)
    # std_msgs/String "hello": header, uint32 length 6, the bytes and their NUL
    hello = w.encode(w.typestore().types["std_msgs/msg/String"]("hello"), "std_msgs/msg/String")
    assert hello == b"\x00\x01\x00\x00" + struct.pack("<I", 6) + b"hello\x00"


@pytest.mark.parametrize("payload", [b"", b"\x00\x01\x00\x00", b"\x00\x01\x00\x00\x01\x02", b"garbage that is long"])
def test_payloads_that_do_not_decode_are_wire_errors_naming_the_topic(payload):
    with pytest.raises(w.Ros2WireError, match="/robot1/scan"):
        w.decode(payload, w.LASER_SCAN, "/robot1/scan")


def test_a_laser_scan_payload_is_not_an_odometry():
    T = w.typestore().types
    header = T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), "laser")
    scan = T[w.LASER_SCAN](header, 0.0, 1.0, 0.5, 0.0, 0.1, 0.05, 8.0, np.ones(3, np.float32), np.zeros(0, np.float32))
    with pytest.raises(w.Ros2WireError):
        w.decode(w.encode(scan, w.LASER_SCAN), w.ODOMETRY, "/odom")


def test_the_attachment_is_33_bytes_sequence_timestamp_gid_length_gid():
    gid = bytes(range(16))
    a = w.Attachment(1, 1_700_000_000_123_456_789, gid)
    packed = a.pack()
    assert len(packed) == 33
    assert packed == struct.pack("<qqB16s", 1, 1_700_000_000_123_456_789, 16, gid)
    assert packed[:8] == b"\x01" + b"\x00" * 7 and packed[16] == 16 and packed[17:] == gid
    assert w.Attachment.unpack(packed) == a


@pytest.mark.parametrize(
    ("data", "says"),
    [
        (None, "no rmw_zenoh attachment"),
        (b"\x01" * 32, "33 bytes, got 32"),
        (struct.pack("<qqB16s", 1, 2, 8, bytes(16)), "GID length is 8"),
    ],
)
def test_missing_or_malformed_attachments_are_refused(data, says):
    with pytest.raises(w.Ros2WireError, match=says):
        w.Attachment.unpack(data, "/scan")


def test_qos_strings_leave_rmw_zenohs_defaults_empty():
    assert w.Qos().keyexpr() == "::,:,:,:,,"
    assert w.Qos(depth=7).keyexpr() == "::,7:,:,:,,"  # the design document's talker
    assert w.MAP.keyexpr() == ":1:,1:,:,:,,"  # REP-2003: reliable, transient local, depth 1
    assert w.SENSOR_DATA.keyexpr() == "2::,5:,:,:,,"
    assert w.Qos(history=w.KEEP_ALL).keyexpr() == "::2,:,:,:,,"


def test_liveliness_tokens_are_the_design_documents():
    node = w.Node(2, "8b20917502ee955ac4476e0266340d5c", 0, "talker")
    assert node.token() == "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
    assert (
        node.endpoint_token(10, "MP", "/chatter", "std_msgs/msg/String", w.Qos(depth=7))
        == f"@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )
    ns = w.Node(0, "abc", 3, "fleetmap_agent", "/robot1")
    assert ns.token() == "@ros2_lv/0/abc/3/3/NN/%/%robot1/fleetmap_agent"
    sub = ns.endpoint_token(4, "MS", "/robot1/scan", w.LASER_SCAN, w.SENSOR_DATA)
    assert sub.startswith(
        "@ros2_lv/0/abc/3/4/MS/%/%robot1/fleetmap_agent/%robot1%scan/sensor_msgs::msg::dds_::LaserScan_/"
    )
    assert sub.endswith("/2::,5:,:,:,,")
    with pytest.raises(ValueError):
        ns.endpoint_token(5, "SS", "/x", "std_msgs/msg/String", w.Qos())


def test_a_gid_is_16_stable_bytes_of_the_token():
    assert len(w.gid_of("@ros2_lv/0/a")) == 16 and w.gid_of("@ros2_lv/0/a") == w.gid_of("@ros2_lv/0/a")
    assert w.gid_of("@ros2_lv/0/a") != w.gid_of("@ros2_lv/0/b")


@pytest.mark.skipif(sys.byteorder != "little", reason="rmw_zenoh copies the halves in the machine's byte order")
def test_a_gid_is_xxh3_128_of_the_token_low_half_first():
    # XXH3-128 of no bytes is 99aa06d3014798d8 6001c324468d497f (high, low: xxHash's own sanity
    # check), of "hello" b5e9c1ad071b3e7f c779cfaa5e523818: rmw_zenoh copies low64, then high64
    assert w.gid_of("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    assert w.gid_of("hello") == bytes.fromhex("1838525eaacf79c77f3e1b07adc1e9b5")
