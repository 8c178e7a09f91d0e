"""The bus messages: round trips, and every kind of bad field refused with its name."""

from __future__ import annotations

import math
import struct
import tracemalloc
from dataclasses import replace

import msgpack
import numpy as np
import pytest
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys, map_key, parse_map_key
from fleetmap.shared.io.messages import (
    BadMessage,
    Component,
    EpochLink,
    FleetEvent,
    GlobalMap,
    LaserRanges,
    LocalMap,
    MergeEdge,
    MergerStep,
    RobotPose,
    Scan,
    SubmapLink,
    decode,
)
from fleetmap.shared.io.wire_decoding import DECODED_BYTES_PER_BYTE, DECODED_SLACK, MAX_PAYLOAD_BYTES
from fleetmap.shared.io.wire_fields import MAX_SEGMENTS
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

SEGMENTS = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 1.0, 2.5], [-3.25, 4.0, 0.5, 0.125]])


def scan() -> Scan:
    ranges = LaserRanges(-math.pi / 2, math.pi / 180, 8.0, np.array([1.5, math.inf, math.nan, 7.25]))
    return Scan("r1", 2, 17, 123.25, SEGMENTS, ranges)


def local_map() -> LocalMap:
    link = EpochLink(1, "kidnap", None)
    return LocalMap("r1", 2, 5, 130.0, SEGMENTS, 12, Transform2D(0.5, -1.0, 0.25), link)


def global_map() -> GlobalMap:
    first = Component("r1/0", ("r1/0", "r2/0"), {"r1/0": Transform2D(), "r2/0": Transform2D(1.0, 2.0, -0.5)}, SEGMENTS)
    second = Component("r3/1", ("r3/1",), {"r3/1": Transform2D()}, SEGMENTS[:1])
    return GlobalMap(7, 140.5, (first, second))


def final_local_map() -> LocalMap:
    """A final submap with its link, scan table and viewpoints (every optional field set)."""
    m = local_map()
    return LocalMap(
        m.robot,
        m.epoch,
        m.version,
        m.stamp,
        m.segments,
        2,
        m.pose,
        submap=3,
        final=True,
        link=SubmapLink(2, Transform2D(4.0, 0.5, 0.1), (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5)),
        scan_indices=np.array([4, 5]),
        scan_stamps=np.array([129.0, 130.0]),
        scan_poses=np.array([[0.0, 0.0, 0.0], [0.5, -1.0, 0.25]]),
    )


def edge() -> MergeEdge:
    return MergeEdge("r1/0/0", "r2/0/1", 1.0, -2.0, 0.5, 12.5, True, 140.0)


def robot_pose() -> RobotPose:
    return RobotPose("r1", 2, 140.0, Transform2D(1.0, 2.0, 3.0), 0)


def event() -> FleetEvent:
    return FleetEvent("epoch", "r1", 12.0, '{"epoch": 2, "first_scan": 40}')


def step() -> MergerStep:
    return MergerStep(9, 140.0, ("r1/2/3", "r2/0/0"), (5, 0), integrations=4, queued=2)


DECODERS = [scan, local_map, final_local_map, global_map, edge, robot_pose, event, step]
"""A message of every schema, for the fuzz tests."""


def wire(message: object) -> dict:
    return msgpack.unpackb(message.to_msgpack(), raw=False)  # type: ignore[attr-defined]


def repack(data: dict) -> bytes:
    return msgpack.packb(data, use_bin_type=True)


def refused(data: dict) -> str:
    with pytest.raises(BadMessage) as info:
        decode(repack(data))
    return str(info.value)


# --- round trips ---


def test_scan_round_trip_keeps_segments_and_raw_ranges():
    back = decode(scan().to_msgpack())
    assert isinstance(back, Scan)
    assert (back.robot, back.epoch, back.index, back.stamp) == ("r1", 2, 17, 123.25)
    np.testing.assert_array_equal(back.segments, SEGMENTS)
    assert back.ranges is not None
    assert back.ranges.ranges.dtype == np.float32
    np.testing.assert_array_equal(back.ranges.ranges, np.array([1.5, math.inf, math.nan, 7.25], dtype=np.float32))
    assert back.ranges.angle_increment == pytest.approx(math.pi / 180)


def test_scan_ranges_convert_to_and_from_a_range_scan():
    rs = RangeScan(3.0, -1.0, 0.5, math.inf, np.array([1.0, 2.0, math.nan]))
    back = decode(Scan("r1", 0, 0, 3.0, SEGMENTS, LaserRanges.from_range_scan(rs)).to_msgpack())
    assert isinstance(back, Scan) and back.ranges is not None
    again = back.ranges.to_range_scan(back.stamp)
    assert (again.stamp, again.angle_min, again.angle_increment, again.range_max) == (3.0, -1.0, 0.5, math.inf)
    np.testing.assert_array_equal(again.ranges, rs.ranges)


def test_local_map_round_trip():
    back = LocalMap.from_msgpack(local_map().to_msgpack())
    assert (back.robot, back.epoch, back.version, back.scans, back.key) == ("r1", 2, 5, 12, "r1/2")
    assert back.pose == Transform2D(0.5, -1.0, 0.25)
    assert back.previous_epoch_link == EpochLink(1, "kidnap", None)
    np.testing.assert_array_equal(back.segments, SEGMENTS)


def test_local_map_viewpoints_round_trip_and_are_optional():
    vp = np.array([[0.0, 0.0, 0.0, -2.0, 2.0], [1.5, -0.5, 0.3, -math.pi, math.pi]])
    back = LocalMap.from_msgpack(replace(local_map(), viewpoints=vp).to_msgpack())
    np.testing.assert_array_equal(back.viewpoints, vp)
    assert LocalMap.from_msgpack(local_map().to_msgpack()).viewpoints is None


def submap(**changes):
    """Submap 3 of r1's epoch 2, final, linked to submap 2, placing two scans."""
    base = dict(
        submap=3,
        final=True,
        link=SubmapLink(2, Transform2D(4.0, 0.5, 0.1), (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-5)),
        scan_indices=np.array([41, 42]),
        scan_stamps=np.array([1_700_000_000.123456, 1_700_000_000.323456]),
        scan_poses=np.array([[0.0, 0.0, 0.0], [0.3, 0.01, 0.02]]),
    )
    return replace(local_map(), **{**base, **changes})


def test_a_submap_round_trips_with_its_link_and_the_scans_it_places():
    back = LocalMap.from_msgpack(submap().to_msgpack())
    assert (back.submap, back.final, back.submap_key, back.key) == (3, True, "r1/2/3", "r1/2")
    assert back.link.transform == Transform2D(4.0, 0.5, 0.1) and back.link.covariance_matrix[2, 2] == 1e-5
    assert back.scan_indices.tolist() == [41, 42]
    assert back.scan_stamps.tolist() == [1_700_000_000.123456, 1_700_000_000.323456], "stamps exact"
    np.testing.assert_array_equal(back.scan_poses, [[0.0, 0.0, 0.0], [0.3, 0.01, 0.02]])


def test_a_local_map_of_version_1_reads_as_an_epochs_first_submap():
    # Version 1: a whole epoch's local map, none of the submap fields.
    data = wire(local_map())
    data["v"] = 1
    for name in ("submap", "final", "link", "scan_indices", "scan_stamps", "scan_poses"):
        data.pop(name, None)
    back = LocalMap.from_msgpack(repack(data))
    assert (back.submap, back.final, back.link, back.scan_indices) == (0, False, None, None)
    assert back.submap_key == "r1/2/0" and back.version == 5


@pytest.mark.parametrize(
    ("changes", "field", "reason"),
    [
        ({"link": SubmapLink(1, Transform2D(), (1, 0, 0, 0, 1, 0, 0, 0, 1))}, "link.submap", "not the submap before"),
        ({"scan_stamps": np.array([1.0])}, "scan_poses", "differ"),
        ({"scan_indices": None}, "scan_indices", "go together"),
        ({"scan_indices": np.array([-1, 2])}, "scan_indices", "negative"),
    ],
)
def test_a_submaps_link_and_scan_table_are_checked(changes, field, reason):
    with pytest.raises(BadMessage, match=reason) as error:
        submap(**changes)
    assert error.value.field == field


@pytest.mark.parametrize(
    "covariance",
    [(1, 0, 0, 0, 1, 0, 0, 0), (1, 2, 0, 0, 1, 0, 0, 0, 1), (1, 0, 0, 0, -1, 0, 0, 0, 1), (math.nan,) * 9],
)
def test_a_link_covariance_that_is_no_covariance_is_refused(covariance):
    with pytest.raises(BadMessage, match="covariance"):
        SubmapLink(0, Transform2D(), covariance)


def test_a_scan_names_its_submap_and_pose_together_and_carries_odometry():
    placed = replace(
        scan(), submap=2, pose=Transform2D(0.1, 0.2, 0.3), odometry=Transform2D(5.0, 6.0, 7.0 - 2 * math.pi)
    )
    back = Scan.from_msgpack(placed.to_msgpack())
    assert (back.submap, back.pose, back.odometry) == (2, placed.pose, placed.odometry)
    with pytest.raises(BadMessage, match="names its submap and its pose"):
        replace(scan(), submap=2)
    assert Scan.from_msgpack(scan().to_msgpack()).odometry is None


def test_a_lost_robot_has_no_pose_in_its_local_map():
    lost = LocalMap("r1", 0, 0, 0.0, SEGMENTS, 1, None)
    assert LocalMap.from_msgpack(lost.to_msgpack()).pose is None


def test_global_map_round_trip():
    back = GlobalMap.from_msgpack(global_map().to_msgpack())
    assert back.seq == 7 and len(back.components) == 2
    first = back.components[0]
    assert first.anchor == "r1/0" and first.members == ("r1/0", "r2/0")
    assert first.poses["r2/0"] == Transform2D(1.0, 2.0, -0.5)
    np.testing.assert_array_equal(first.segments, SEGMENTS)
    assert back.component_of("r3/1") == 1 and back.component_of("r9/0") is None


def test_value_messages_round_trip_equal():
    for message in (
        MergeEdge("r1/0", "r2/3", 1.0, -2.0, 0.5, 12.5, True, 9.0),
        RobotPose("r2", 3, 9.5, Transform2D(1.0, 2.0, 3.0), 0),
        RobotPose("r2", 4, 9.5, None, None),
        FleetEvent("join", "r2", 1.0, "fleet/default/alive/r2"),
        FleetEvent("merger_start", None, 2.0),
    ):
        assert type(message).from_msgpack(message.to_msgpack()) == message
    for step in (
        MergerStep(7, 9.5, ("r1/0", "r2/3"), (4, 0), integrations=3, queued=12),
        MergerStep(8, 9.5, (), ()),
        MergerStep(9, 9.5, ("r1/0/4", "r2/3/0"), (1, 7)),
    ):
        back = MergerStep.from_msgpack(step.to_msgpack())
        fields = ("seq", "stamp", "maps", "versions", "integrations", "queued")
        assert [getattr(back, f) for f in fields] == [getattr(step, f) for f in fields]


def test_a_merger_step_without_its_integration_counts_reads_as_one_that_did_all():
    # A step without a budget: no integrations or queued field (a replay does all).
    data = wire(MergerStep(7, 9.5, ("r1/0",), (4,)))
    del data["integrations"], data["queued"]
    step = decode(msgpack.packb(data))
    assert isinstance(step, MergerStep) and step.integrations is None and step.queued is None
    with pytest.raises(BadMessage, match="integrations"):
        MergerStep(7, 9.5, ("r1/0",), (4,), integrations=-1)


def test_payload_is_a_msgpack_map_with_schema_version_and_packed_float64_segments():
    data = wire(local_map())
    assert data["schema"] == "fleetmap.LocalMap" and data["v"] == 2
    assert data["segments"] == struct.pack("<12d", *SEGMENTS.ravel())
    assert data["pose"] == {"x": 0.5, "y": -1.0, "theta": 0.25}


def test_decoded_segments_are_read_only():
    back = LocalMap.from_msgpack(local_map().to_msgpack())
    with pytest.raises(ValueError):
        back.segments[0, 0] = 5.0


def test_unknown_fields_are_ignored_so_senders_can_add_optional_ones():
    data = wire(local_map())
    data["coverage"] = 0.5
    assert LocalMap.from_msgpack(repack(data)).version == 5


def test_from_msgpack_of_another_type_is_refused():
    with pytest.raises(BadMessage, match=r"expected fleetmap\.LocalMap, got fleetmap\.Scan"):
        LocalMap.from_msgpack(scan().to_msgpack())


# --- validation names the field and the reason ---


def test_segments_not_a_multiple_of_four_floats():
    data = wire(local_map())
    data["segments"] = data["segments"][:-8]
    assert refused(data) == "fleetmap.LocalMap field 'segments': 11 floats is not a multiple of 4"


@pytest.mark.parametrize(
    ("row", "reason"),
    [
        ([0.0, 0.0, math.nan, 1.0], "segment 1 has a NaN or infinite coordinate"),
        ([0.0, 0.0, math.inf, 1.0], "segment 1 has a NaN or infinite coordinate"),
        ([2.0, 3.0, 2.0, 3.0], "segment 1 has zero length"),
    ],
)
def test_bad_segments_are_refused(row, reason):
    data = wire(local_map())
    bad = SEGMENTS.copy()
    bad[1] = row
    data["segments"] = bad.astype("<f8").tobytes()
    assert refused(data) == f"fleetmap.LocalMap field 'segments': {reason}"


def test_too_many_segments_are_refused_before_decoding_them():
    data = wire(local_map())
    data["segments"] = bytes(32 * (MAX_SEGMENTS + 1))
    assert "200001 segments is more than 200000" in refused(data)


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("robot", "R1", "'R1' is not a robot id"),
        ("robot", "r" * 33, "is not a robot id"),
        ("robot", 7, "expected a robot id (string), got int"),
        ("epoch", -1, "expected an integer from 0 to 999999999999999999, got -1"),
        ("epoch", 10**18, "expected an integer from 0 to 999999999999999999, got 1000000000000000000"),
        ("stamp", 1.7e12, "after the year 2262 (a clock in milliseconds?)"),
        ("epoch", 1.5, "expected a non-negative integer, got float"),
        ("epoch", True, "expected a non-negative integer, got bool"),
        ("version", "3", "expected a non-negative integer, got str"),
        ("stamp", math.nan, "nan is not finite"),
        ("stamp", -1.0, "-1.0 is below 0.0"),
        ("scans", None, "expected a non-negative integer, got NoneType"),
        ("pose", {"x": 1.0, "y": 2.0}, "missing theta"),
        ("pose", [1.0, 2.0, 3.0], "expected a transform {x, y, theta}, got list"),
        ("viewpoints", b"\x00" * 48, "6 floats is not a multiple of 5"),
        ("viewpoints", [[0.0, 0.0, 0.0, -1.0]], "expected shape (n, 5), got (1, 4)"),
        ("viewpoints", [[0.0, math.nan, 0.0, -1.0, 1.0]], "viewpoint 0 has a NaN or infinite coordinate"),
        ("viewpoints", "here", "expected packed float64 viewpoints, got str"),
    ],
)
def test_bad_local_map_fields_are_named(field, value, reason):
    data = wire(local_map())
    data[field] = value
    text = refused(data)
    assert text.startswith(f"fleetmap.LocalMap field '{field}")
    assert reason in text


def test_missing_field_is_named():
    data = wire(local_map())
    del data["version"]
    assert refused(data) == "fleetmap.LocalMap field 'version': missing"


def test_nested_fields_are_named_with_their_path():
    data = wire(global_map())
    data["components"][0]["poses"]["r2/0"]["x"] = math.inf
    assert refused(data) == "fleetmap.GlobalMap field 'components[0].poses[r2/0].x': inf is not finite"


def test_previous_epoch_link_must_point_back():
    with pytest.raises(BadMessage, match=r"'previous_epoch_link\.epoch': 2 is not before epoch 2"):
        LocalMap("r1", 2, 0, 0.0, SEGMENTS, 1, None, EpochLink(2))


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda c: c.update(anchor="r9/0"), "'r9/0' is not one of the members"),
        (lambda c: c.update(members=["r1/0", "r1/0", "r2/0"]), "a map is listed twice"),
        (lambda c: c["poses"].pop("r2/0"), "members without a pose: ['r2/0']"),
        (lambda c: c.update(members=["r1/0", "r2/x"]), "'r2/x' is not a map key <robot>/<epoch>"),
    ],
)
def test_inconsistent_components_are_refused(change, reason):
    data = wire(global_map())
    change(data["components"][0])
    assert reason in refused(data)


def test_a_map_in_two_components_is_refused():
    data = wire(global_map())
    data["components"][1] = data["components"][0]
    assert "'r1/0' is in two components" in refused(data)


def test_edges_need_two_different_map_keys_and_a_non_negative_value():
    with pytest.raises(BadMessage, match="'a': 'r1' is not a map key"):
        MergeEdge("r1", "r2/0", 0.0, 0.0, 0.0, 1.0, True, 0.0)
    with pytest.raises(BadMessage, match="two different maps"):
        MergeEdge("r1/0", "r1/0", 0.0, 0.0, 0.0, 1.0, True, 0.0)
    with pytest.raises(BadMessage, match=r"'value': -1\.0 is below 0\.0"):
        MergeEdge("r1/0", "r2/0", 0.0, 0.0, 0.0, -1.0, True, 0.0)
    with pytest.raises(BadMessage, match="'valid': expected true or false, got int"):
        MergeEdge("r1/0", "r2/0", 0.0, 0.0, 0.0, 1.0, 1, 0.0)  # type: ignore[arg-type]


def test_an_unknown_pose_has_no_component_and_a_known_one_needs_it():
    with pytest.raises(BadMessage, match="'component'"):
        RobotPose("r1", 0, 0.0, None, 0)
    with pytest.raises(BadMessage, match="'component'"):
        RobotPose("r1", 0, 0.0, Transform2D(), None)


def test_event_kinds_and_detail_length_are_checked():
    with pytest.raises(BadMessage, match="'kind': 'teleport' is not one of"):
        FleetEvent("teleport", "r1", 0.0)
    with pytest.raises(BadMessage, match="'detail': 257 characters is more than 256"):
        FleetEvent("join", "r1", 0.0, "x" * 257)


def test_laser_ranges_are_checked():
    with pytest.raises(BadMessage, match="'angle_increment': is zero"):
        LaserRanges(0.0, 0.0, 8.0, np.ones(3))
    with pytest.raises(BadMessage, match="'range_max'"):
        LaserRanges(0.0, 0.1, -1.0, np.ones(3))
    data = wire(scan())
    data["ranges"]["ranges"] = b"\x00" * 7
    assert refused(data) == "fleetmap.Scan field 'ranges.ranges': 7 bytes is not a whole number of float32"


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"", "not msgpack"),
        (b"\xc1", "not msgpack"),
        (msgpack.packb([1, 2]), "expected a msgpack map, got list"),
        (msgpack.packb({"schema": "fleetmap.Teleport", "v": 1}), "'fleetmap.Teleport' is not a fleetmap message"),
        (msgpack.packb({"v": 1}), "message field .schema.: missing"),
        (msgpack.packb({"schema": "fleetmap.Scan", "v": 2}), "version 2 is not one this fleetmap reads"),
        (msgpack.packb({1: 2}), "not msgpack"),
    ],
)
def test_payloads_that_are_not_messages(payload, reason):
    with pytest.raises(BadMessage, match=reason):
        decode(payload)


def test_bad_message_is_bad_input_so_the_cli_reports_it_as_such():
    assert issubclass(BadMessage, BadInput)


def test_messages_built_in_code_are_validated_too():
    with pytest.raises(BadMessage, match=r"fleetmap\.Scan field 'segments'"):
        Scan("r1", 0, 0, 0.0, np.array([[0.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_array_equal(Scan("r1", 0, 0, 0.0, []).segments, np.zeros((0, 4)))


# --- keys ---


def test_keys_build_and_parse_back():
    keys = FleetKeys("lab-2")
    assert keys.scan("r1") == "fleet/lab-2/robots/r1/scan"
    assert keys.alive("r1") == "fleet/lab-2/alive/r1"
    assert keys.everything == "fleet/lab-2/**"
    for key, kind, robot in [
        (keys.scan("r1"), "scan", "r1"),
        (keys.localmap("r_2"), "localmap", "r_2"),
        (keys.pose("r3"), "pose", "r3"),
        (keys.robot_events("r3"), "robot_events", "r3"),
        (keys.globalmap, "globalmap", None),
        (keys.edges, "edges", None),
        (keys.state, "state", None),
        (keys.events, "events", None),
        (keys.alive("r4"), "alive", "r4"),
        (keys.service("merger"), "services", "merger"),
    ]:
        parsed = keys.parse(key)
        assert (parsed.kind, parsed.robot) == (kind, robot)


@pytest.mark.parametrize(
    "key",
    ["fleet/other/robots/r1/scan", "fleet/lab-2/robots/R1/scan", "fleet/lab-2/robots/r1/odom", "fleet/lab-2"],
)
def test_keys_of_other_fleets_or_kinds_are_not_parsed(key):
    with pytest.raises(BadInput):
        FleetKeys("lab-2").parse(key)


def test_fleet_and_robot_names_are_validated():
    with pytest.raises(BadInput, match="fleet"):
        FleetKeys("Lab 2")
    with pytest.raises(BadInput, match="robot"):
        FleetKeys().scan("r/1")
    with pytest.raises(BadInput, match="robot"):
        FleetKeys().alive("*")


def test_map_keys():
    assert map_key("r1", 3) == "r1/3"
    assert parse_map_key("r1/3") == ("r1", 3)
    for bad in ("r1/03", "r1/-1", "r1", "R1/0"):
        with pytest.raises(BadInput):
            parse_map_key(bad)


# --- fuzz ---


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=512))
def test_random_bytes_decode_or_raise_bad_message(data):
    try:
        message = decode(data)
    except BadMessage:
        return
    assert message.SCHEMA.startswith("fleetmap.")


FIELD_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats()
    | st.text(max_size=40)
    | st.binary(max_size=64)
    | st.sampled_from(["r1", "r1/0", "r2/3"]),
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(
            st.sampled_from(["x", "y", "theta", "anchor", "members", "poses", "segments", "epoch", "reason"]),
            children,
            max_size=5,
        )
    ),
    max_leaves=12,
)


@pytest.mark.slow  # a fuzz test: hundreds of examples
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from(DECODERS),
    st.dictionaries(st.text(min_size=1, max_size=12), FIELD_VALUES, max_size=3),
    st.data(),
)
def test_messages_with_random_fields_decode_or_raise_bad_message(make, extra, data):
    """Well-formed maps of a real schema with some fields replaced by anything at all."""
    fields = wire(make())
    names = sorted(k for k in fields if k not in ("schema", "v"))
    for name in data.draw(st.lists(st.sampled_from(names), max_size=3)):
        fields[name] = data.draw(FIELD_VALUES)
    fields.update({k: v for k, v in extra.items() if k not in ("schema", "v")})
    try:
        message = decode(repack(fields))
    except BadMessage:
        return
    assert fields["schema"] == message.SCHEMA


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(*[st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)] * 4), min_size=0, max_size=50
    ).filter(lambda rows: all(math.hypot(r[2] - r[0], r[3] - r[1]) > 1e-3 for r in rows)),
    st.integers(min_value=0, max_value=2**63 - 1),
)
def test_any_valid_local_map_round_trips_exactly(rows, version):
    segments = np.array(rows, dtype=np.float64).reshape(-1, 4)
    message = LocalMap("r1", 0, version, 1.0, segments, 1)
    back = LocalMap.from_msgpack(message.to_msgpack())
    assert back.version == version
    np.testing.assert_array_equal(back.segments, segments)
    assert back.to_msgpack() == message.to_msgpack()


def test_a_payload_that_would_blow_up_when_unpacked_is_refused_from_its_header():
    # a big payload, and a small one declaring millions of msgpack items: refused before anything of
    # that size is allocated (docs/decisions/003-a-fleet-that-lets-in-only-its-own.md)
    with pytest.raises(BadMessage, match=f"is more than {MAX_PAYLOAD_BYTES}"):
        decode(b"\x00" * (MAX_PAYLOAD_BYTES + 1))
    huge_array = b"\x81\xa8segments\xdd" + (50_000_000).to_bytes(4, "big")  # map {segments: array32(5e7)}
    with pytest.raises(BadMessage, match="exceeds max_array_len"):
        decode(huge_array)
    with pytest.raises(BadMessage, match="not msgpack"):
        decode(b"\x91" * 100_000 + b"\x00")  # nested 100,000 deep


def _decoding_peak(payload: bytes) -> tuple[float, str]:
    """Peak bytes allocated while decoding ``payload``, and why it was refused."""
    tracemalloc.start()
    try:
        decode(payload)
        reason = ""
    except BadMessage as exc:
        reason = str(exc)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak, reason


@pytest.mark.parametrize(
    ("field", "bomb", "refused"),
    [
        # a name no LocalMap field has: skipped over, never decoded
        ("x", [[[]] * 60_000] * 10, "fleetmap.LocalMap field 'robot': missing"),
        # a field that is packed bytes on the wire: refused from the array's first byte
        ("segments", [[[]] * 60_000] * 10, "fleetmap.LocalMap field 'segments': expected one value or packed bytes"),
        # a field that is a map: counted as it decodes, refused past the budget
        ("link", [{"": ""}] * 200_000, "message: 600"),
    ],
)
def test_a_payload_packing_millions_of_items_decodes_into_a_bounded_multiple_of_its_size(field, bomb, refused):
    # each packed item is one byte on the wire and 56 or more as a Python object: unbounded, a 16 MB
    # payload took over a gigabyte in every subscriber
    payload = msgpack.packb({"schema": "fleetmap.LocalMap", "v": 2, field: bomb})
    peak, reason = _decoding_peak(payload)
    assert peak < DECODED_BYTES_PER_BYTE * len(payload) + DECODED_SLACK + 1_000_000 < 32 * len(payload), peak
    assert reason.startswith(refused), reason


@pytest.mark.slow  # one of the fast suite's slowest (1.1-1.5 s): CI runs it with the slow ones
def test_messages_as_sent_decode_within_their_budget():
    rng = np.random.default_rng(3)
    members = [f"r{i}/{e}" for i in range(100) for e in range(200)]
    components = [
        Component(m[0], tuple(m), {k: Transform2D(1.0, 2.0, 0.5) for k in m}, rng.random((40, 4)) + np.ones(4))
        for m in (members[i : i + 20] for i in range(0, len(members), 20))
    ]
    global_map = GlobalMap(7, 1.0, tuple(components)).to_msgpack()
    step = MergerStep(3, 1.0, tuple(members), tuple(range(len(members)))).to_msgpack()
    for payload in (global_map, step):
        assert len(payload) > 100_000
        assert decode(payload).to_msgpack() == payload


def test_a_global_map_pickles_to_the_same_map() -> None:
    # a session's log goes to the process that writes its files (fleetmap map): its components'
    # poses (a read-only mapping) come back as the same poses, still read-only
    import pickle

    before = global_map()
    after = pickle.loads(pickle.dumps(before))
    assert [c.poses for c in after.components] == [dict(c.poses) for c in before.components]
    assert [c.members for c in after.components] == [c.members for c in before.components]
    assert all(np.array_equal(a.segments, b.segments) for a, b in zip(after.components, before.components, strict=True))
    with pytest.raises(TypeError):
        after.components[0].poses["r9/0"] = Transform2D()
