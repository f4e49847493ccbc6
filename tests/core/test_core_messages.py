"""rce.messages: the message registry, the JSON codec and ROS 1 serialization."""
from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from rce.plumbing.errors import MessageError
from rce.messages import MessageRegistry, default_registry, store_name, wire_name


def msg_error(fn, *args) -> str:
    with pytest.raises(MessageError) as ei:
        fn(*args)
    assert ei.value.code == "message"
    return ei.value.message


# -- names --------------------------------------------------------------------------------------
@pytest.mark.parametrize("wire, store", [
    ("std_msgs/String", "std_msgs/msg/String"),
    ("/std_msgs/String/", "std_msgs/msg/String"),
    ("std_msgs/msg/String", "ros2:std_msgs/msg/String"),     # ROS 2's form names a ROS 2 type (CDR)
    ("Test/srv/StringEcho", "ros2:Test/srv/StringEcho"),
])
def test_store_name(wire, store):
    assert store_name(wire) == store


@pytest.mark.parametrize("bad", ["String", "a/b/c", "a//b", "/", "", "a/x/b", 5, None])
def test_store_name_malformed(bad):
    msg = msg_error(store_name, bad)
    assert "std_msgs/String" in msg or "pkg/Name" in msg


def test_wire_name():
    assert wire_name("geometry_msgs/msg/Pose") == "geometry_msgs/Pose"


def test_default_registry_is_one_instance():
    assert default_registry() is default_registry()


# -- unknown classes ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["nope_msgs/Nothing", "std_msgs/Strin"])
def test_unknown_message_class(reg, name):
    msg = msg_error(reg.msg_type, name)
    assert "unknown message class" in msg and repr(name) in msg


def test_malformed_class_name(reg):
    assert "malformed message class 'String'" in msg_error(reg.msg_type, "String")


def test_unknown_service_class(reg):
    assert "unknown service class 'nope/Srv'" in msg_error(reg.srv_types, "nope/Srv")
    assert reg.is_service("nope/Srv") is False
    assert reg.is_service("std_msgs/String") is False


def test_known_classes(reg):
    assert reg.msg_type("std_msgs/String") == "std_msgs/msg/String"
    assert reg.msg_type("sensor_msgs/LaserScan") == "sensor_msgs/msg/LaserScan"
    assert reg.msg_type("sensor_msgs/msg/LaserScan") == "ros2:sensor_msgs/msg/LaserScan"


# -- round trips --------------------------------------------------------------------------------
def test_string_round_trip_and_bytes(reg, ts):
    t = reg.msg_type("std_msgs/String")
    data = reg.json_to_bytes(t, {"data": "héllo"})
    ref = bytes(ts.serialize_ros1(ts.types["std_msgs/msg/String"](data="héllo"), "std_msgs/msg/String"))
    assert data == ref == len("héllo".encode()).to_bytes(4, "little") + "héllo".encode()
    assert reg.bytes_to_json(t, data) == {"data": "héllo"}


def test_missing_fields_take_defaults(reg):
    t = reg.msg_type("std_msgs/String")
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, {})) == {"data": ""}
    t = reg.msg_type("sensor_msgs/LaserScan")
    j = reg.bytes_to_json(t, reg.json_to_bytes(t, {}))
    assert j["header"] == {"seq": 0, "stamp": {"secs": 0, "nsecs": 0}, "frame_id": ""}
    assert j["ranges"] == [] and j["angle_min"] == 0.0


def pose_cov_json() -> dict:
    return {"header": {"seq": 7, "stamp": {"secs": 1700000000, "nsecs": 123456789}, "frame_id": "map"},
            "pose": {"pose": {"position": {"x": 1.5, "y": -2.25, "z": 0.0},
                              "orientation": {"x": 0.0, "y": 0.0, "z": 0.7071067811865476, "w": 0.7071067811865476}},
                     "covariance": [float(i) / 10 for i in range(36)]}}


def test_pose_with_covariance_round_trip(reg, ts):
    t = reg.msg_type("geometry_msgs/PoseWithCovarianceStamped")
    j = pose_cov_json()
    data = reg.json_to_bytes(t, j)
    assert reg.bytes_to_json(t, data) == j
    # the same message built with rosbags directly serializes to the same bytes
    T = ts.types
    ref = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=T["std_msgs/msg/Header"](
            seq=7, stamp=T["builtin_interfaces/msg/Time"](sec=1700000000, nanosec=123456789), frame_id="map"),
        pose=T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.5, y=-2.25, z=0.0),
                                             orientation=T["geometry_msgs/msg/Quaternion"](
                                                 x=0.0, y=0.0, z=0.7071067811865476, w=0.7071067811865476)),
            covariance=np.array([float(i) / 10 for i in range(36)], dtype=np.float64)))
    assert data == bytes(ts.serialize_ros1(ref, t))


def test_header_stamp_accepts_sec_nanosec(reg):
    t = reg.msg_type("geometry_msgs/PoseWithCovarianceStamped")
    j = pose_cov_json()
    j2 = json.loads(json.dumps(j))
    j2["header"]["stamp"] = {"sec": 1700000000, "nanosec": 123456789}
    assert reg.json_to_bytes(t, j2) == reg.json_to_bytes(t, j)
    # output is always {secs, nsecs}
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, j2))["header"]["stamp"] == {"secs": 1700000000, "nsecs": 123456789}


def test_laserscan_round_trip_with_nan_and_float32(reg, ts):
    t = reg.msg_type("sensor_msgs/LaserScan")
    j = {"header": {"seq": 1, "stamp": {"secs": 5, "nsecs": 0}, "frame_id": "laser"},
         "angle_min": -1.5, "angle_max": 1.5, "angle_increment": 0.5, "time_increment": 0.0,
         "scan_time": 0.1, "range_min": 0.1, "range_max": 10.0,
         "ranges": [1.0, 2.5, None, 0.25, 3], "intensities": [100.0]}
    data = reg.json_to_bytes(t, j)
    back = reg.bytes_to_json(t, data)
    assert back["ranges"] == [1.0, 2.5, None, 0.25, 3.0]        # NaN travels as null
    assert back["intensities"] == [100.0]
    assert math.isclose(back["scan_time"], 0.1, rel_tol=1e-6)    # float32 precision
    T = ts.types
    ref = T["sensor_msgs/msg/LaserScan"](
        header=T["std_msgs/msg/Header"](
            seq=1, stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="laser"),
        angle_min=-1.5, angle_max=1.5, angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1,
        range_max=10.0, ranges=np.array([1.0, 2.5, np.nan, 0.25, 3.0], dtype=np.float32),
        intensities=np.array([100.0], dtype=np.float32))
    assert data == bytes(ts.serialize_ros1(ref, t))


def image_json(data) -> dict:
    return {"header": {"seq": 0, "stamp": {"secs": 1, "nsecs": 2}, "frame_id": "cam"},
            "height": 2, "width": 3, "encoding": "mono8", "is_bigendian": 0, "step": 3, "data": data}


def test_image_data_base64_out_list_or_base64_in(reg, ts):
    t = reg.msg_type("sensor_msgs/Image")
    pixels = [0, 1, 2, 253, 254, 255]
    b64 = base64.b64encode(bytes(pixels)).decode()
    from_list = reg.json_to_bytes(t, image_json(pixels))
    from_b64 = reg.json_to_bytes(t, image_json(b64))
    assert from_list == from_b64
    back = reg.bytes_to_json(t, from_list)
    assert back["data"] == b64 and back == image_json(b64)
    T = ts.types
    ref = T["sensor_msgs/msg/Image"](
        header=T["std_msgs/msg/Header"](
            seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="cam"),
        height=2, width=3, encoding="mono8", is_bigendian=0, step=3, data=np.array(pixels, dtype=np.uint8))
    assert from_list == bytes(ts.serialize_ros1(ref, t))


def test_image_empty_data(reg):
    t = reg.msg_type("sensor_msgs/Image")
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, image_json("")))["data"] == ""
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, image_json([])))["data"] == ""


def test_int32_multiarray_round_trip(reg, ts):
    t = reg.msg_type("std_msgs/Int32MultiArray")
    j = {"layout": {"dim": [{"label": "rows", "size": 2, "stride": 6}, {"label": "cols", "size": 3, "stride": 3}],
                    "data_offset": 0},
         "data": [-(2**31), -1, 0, 1, 42, 2**31 - 1]}
    data = reg.json_to_bytes(t, j)
    assert reg.bytes_to_json(t, data) == j
    T = ts.types
    ref = T["std_msgs/msg/Int32MultiArray"](
        layout=T["std_msgs/msg/MultiArrayLayout"](dim=[
            T["std_msgs/msg/MultiArrayDimension"](label="rows", size=2, stride=6),
            T["std_msgs/msg/MultiArrayDimension"](label="cols", size=3, stride=3)], data_offset=0),
        data=np.array(j["data"], dtype=np.int32))
    assert data == bytes(ts.serialize_ros1(ref, t))


def test_integral_float_is_accepted_for_int(reg):
    t = reg.msg_type("std_msgs/Int32MultiArray")
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, {"data": [3.0]}))["data"] == [3]


def test_output_is_json_serializable(reg):
    t = reg.msg_type("geometry_msgs/PoseWithCovarianceStamped")
    out = reg.bytes_to_json(t, reg.json_to_bytes(t, pose_cov_json()))
    assert json.loads(json.dumps(out, allow_nan=False)) == out


# -- errors: outer class and full field path ----------------------------------------------------
PWCS = "geometry_msgs/PoseWithCovarianceStamped"


@pytest.mark.parametrize("cls, obj, parts", [
    (PWCS, {"header": {"frame_id": 5}}, ["field 'header.frame_id'", "string", "int"]),
    (PWCS, {"pose": {"pose": {"position": {"x": "1"}}}}, ["field 'pose.pose.position.x'", "number", "str"]),
    (PWCS, {"pose": {"pose": {"position": {"x": True}}}}, ["field 'pose.pose.position.x'", "number"]),
    (PWCS, {"pose": {"pose": {"position": {"q": 1}}}}, ["unknown field 'pose.pose.position.q'"]),
    (PWCS, {"extra": 1}, ["unknown field 'extra'"]),
    (PWCS, {"header": {"seq": -1}}, ["field 'header.seq'", "out of range for uint32"]),
    (PWCS, {"header": {"seq": 2**32}}, ["field 'header.seq'", "out of range"]),
    (PWCS, {"header": {"seq": 1.5}}, ["field 'header.seq'", "integer (uint32)", "1.5"]),
    (PWCS, {"header": {"seq": True}}, ["field 'header.seq'", "integer"]),
    (PWCS, {"header": 3}, ["field 'header'", "object", "int"]),
    (PWCS, {"header": {"stamp": {"secs": "now"}}}, ["field 'header.stamp.secs'", "integer"]),
    (PWCS, {"header": {"stamp": {"sec": "now"}}}, ["field 'header.stamp.sec'", "integer"]),
    (PWCS, {"header": {"stamp": {"nsecs": -1}}}, ["field 'header.stamp.nsecs'", "out of range"]),
    (PWCS, {"header": {"stamp": {"secs": 1, "nsec": 5}}}, ["unknown field 'header.stamp.nsec'"]),
    (PWCS, {"header": {"stamp": 12}}, ["field 'header.stamp'", "object"]),
    (PWCS, {"pose": {"covariance": [0.0] * 35}}, ["field 'pose.covariance'", "36 items", "35"]),
    (PWCS, {"pose": {"covariance": [0.0] * 37}}, ["field 'pose.covariance'", "36 items", "37"]),
    (PWCS, {"pose": {"covariance": [0.0] * 35 + ["x"]}}, ["field 'pose.covariance[35]'", "number"]),
    (PWCS, {"pose": {"covariance": "0"}}, ["field 'pose.covariance'", "list"]),
    (PWCS, {"pose": {"covariance": [0.0] * 35 + [True]}}, ["field 'pose.covariance[35]'", "number"]),
    (PWCS, {"pose": {"covariance": [0.0] * 35 + [10**400]}}, ["field 'pose.covariance[35]'", "1329 bits"]),
    (PWCS, {"pose": {"pose": {"position": {"x": -10**400}}}}, ["field 'pose.pose.position.x'", "float64"]),
    ("sensor_msgs/Image", {"data": "not base64!"}, ["field 'data'", "base64"]),
    ("sensor_msgs/Image", {"data": [1, 256]}, ["field 'data[1]'", "out of range for uint8"]),
    ("sensor_msgs/Image", {"data": 5}, ["field 'data'", "list or base64 string"]),
    ("sensor_msgs/Image", {"is_bigendian": -1}, ["field 'is_bigendian'", "out of range"]),
    ("sensor_msgs/LaserScan", {"ranges": [1.0, "x"]}, ["field 'ranges[1]'", "number"]),
    ("sensor_msgs/LaserScan", {"ranges": {"a": 1}}, ["field 'ranges'", "list"]),
    ("std_msgs/Int32MultiArray", {"data": [1, 2**31]}, ["field 'data[1]'", "out of range for int32"]),
    ("std_msgs/Int32MultiArray", {"data": [-2**31 - 1, 0]}, ["field 'data[0]'", "out of range for int32"]),
    ("std_msgs/Int32MultiArray", {"data": [1, 2.5]}, ["field 'data[1]'", "integer"]),
    ("std_msgs/Int32MultiArray", {"data": [1, False]}, ["field 'data[1]'", "integer"]),
    ("std_msgs/Int32MultiArray", {"layout": {"dim": [{}, {"size": -1}]}},
     ["field 'layout.dim[1].size'", "out of range"]),
    ("std_msgs/Int32MultiArray", {"layout": {"dim": [{"lable": "x"}]}}, ["unknown field 'layout.dim[0].lable'"]),
    ("std_msgs/Int32MultiArray", {"layout": {"dim": {"label": "x"}}}, ["field 'layout.dim'", "list"]),
    ("std_msgs/String", {"data": None}, ["field 'data'", "string"]),
    ("std_msgs/Bool", {"data": 1}, ["field 'data'", "true or false"]),
])
def test_errors_name_outer_class_and_field_path(reg, cls, obj, parts):
    msg = msg_error(reg.json_to_bytes, reg.msg_type(cls), obj)
    assert msg.startswith(cls + ": "), msg
    for p in parts:
        assert p in msg, (p, msg)


@pytest.mark.parametrize("obj", [[], "x", None, 5])
def test_message_must_be_an_object(reg, obj):
    msg = msg_error(reg.from_json, "std_msgs/msg/String", obj)
    assert msg.startswith("std_msgs/String: ") and "JSON object" in msg


def test_deserialize_garbage_names_class(reg):
    msg = msg_error(reg.bytes_to_json, "geometry_msgs/msg/PoseWithCovarianceStamped", b"\x01\x02")
    assert "2 bytes" in msg and "geometry_msgs/PoseWithCovarianceStamped" in msg


def test_serialize_bad_instance_names_class(reg):
    assert "std_msgs/String" in msg_error(reg.serialize, "std_msgs/msg/String", object())


def test_error_does_not_poison_the_codec(reg):
    t = reg.msg_type("std_msgs/String")
    msg_error(reg.json_to_bytes, t, {"data": 1})
    assert reg.bytes_to_json(t, reg.json_to_bytes(t, {"data": "ok"})) == {"data": "ok"}


# -- registration ---------------------------------------------------------------------------------
def test_register_msg_and_round_trip(ts):
    r = MessageRegistry()
    r.register_msg("my_pkg/Reading", "Header header\nfloat64 value\nstring[] tags\nint16[3] xyz\nuint8[] blob\n")
    t = r.msg_type("my_pkg/Reading")
    j = {"header": {"seq": 1, "stamp": {"secs": 2, "nsecs": 3}, "frame_id": "f"}, "value": 0.5,
         "tags": ["a", "b"], "xyz": [1, -2, 3], "blob": base64.b64encode(b"\x00\x09").decode()}
    data = r.json_to_bytes(t, j)
    assert r.bytes_to_json(t, data) == j
    # defaults for a fixed-size array
    assert r.bytes_to_json(t, r.json_to_bytes(t, {}))["xyz"] == [0, 0, 0]
    assert "field 'xyz'" in msg_error(r.json_to_bytes, t, {"xyz": [1, 2]})
    # the serialization matches rosbags' for the same definition
    from rosbags.typesys import get_types_from_msg
    ts2 = get_typestore(Stores.ROS1_NOETIC)
    ts2.register(get_types_from_msg("Header header\nfloat64 value\nstring[] tags\nint16[3] xyz\nuint8[] blob\n",
                                    "my_pkg/msg/Reading"))
    T = ts2.types
    ref = T["my_pkg/msg/Reading"](
        header=T["std_msgs/msg/Header"](seq=1, stamp=T["builtin_interfaces/msg/Time"](sec=2, nanosec=3), frame_id="f"),
        value=0.5, tags=["a", "b"], xyz=np.array([1, -2, 3], dtype=np.int16), blob=np.array([0, 9], dtype=np.uint8))
    assert data == bytes(ts2.serialize_ros1(ref, "my_pkg/msg/Reading"))


def test_register_msg_referring_to_own_package_and_fixed_array_of_messages():
    r = MessageRegistry()
    r.register_msg("my_pkg/Cell", "int32 row\nint32 col")
    r.register_msg("my_pkg/Path", "Cell[] cells\nCell[2] ends\ngeometry_msgs/Point origin")
    t = r.msg_type("my_pkg/Path")
    j = {"cells": [{"row": 1, "col": 2}], "ends": [{"row": 0, "col": 0}, {"row": 3, "col": 4}],
         "origin": {"x": 1.0, "y": 2.0, "z": 0.0}}
    assert r.bytes_to_json(t, r.json_to_bytes(t, j)) == j
    assert r.bytes_to_json(t, r.json_to_bytes(t, {}))["ends"] == [{"row": 0, "col": 0}] * 2
    msg = msg_error(r.json_to_bytes, t, {"ends": [{}]})
    assert msg.startswith("my_pkg/Path: ") and "field 'ends'" in msg and "2 items" in msg
    msg = msg_error(r.json_to_bytes, t, {"cells": [{}, {"row": "x"}]})
    assert msg.startswith("my_pkg/Path: ") and "field 'cells[1].row'" in msg


def test_register_srv():
    r = MessageRegistry()
    r.register_srv("my_pkg/AddTwo", "int64 a\nint64 b\n---\nint64 sum\n")
    req, resp = r.srv_types("my_pkg/AddTwo")
    assert (req, resp) == ("my_pkg/msg/AddTwoRequest", "my_pkg/msg/AddTwoResponse")
    assert r.is_service("my_pkg/AddTwo")
    assert r.bytes_to_json(req, r.json_to_bytes(req, {"a": 1, "b": -2})) == {"a": 1, "b": -2}
    assert r.bytes_to_json(resp, r.json_to_bytes(resp, {"sum": -1})) == {"sum": -1}
    assert "unknown field 'sum'" in msg_error(r.json_to_bytes, req, {"sum": 1})


def test_register_srv_with_empty_halves():
    r = MessageRegistry()
    r.register_srv("my_pkg/Trigger", "---\n")
    req, resp = r.srv_types("my_pkg/Trigger")
    assert r.json_to_bytes(req, {}) == b"" and r.json_to_bytes(resp, {}) == b""


def test_register_srv_without_separator():
    r = MessageRegistry()
    msg = msg_error(r.register_srv, "my_pkg/Bad", "int32 a\nint32 b\n")
    assert "'my_pkg/Bad'" in msg and "---" in msg
    assert not r.is_service("my_pkg/Bad")


@pytest.mark.parametrize("text", ["int32", "int32[ x", "int32 a\n---\nint32 b"])
def test_register_msg_unparsable(text):
    r = MessageRegistry()
    msg = msg_error(r.register_msg, "my_pkg/Bad", text)
    assert "'my_pkg/Bad'" in msg
    msg_error(r.msg_type, "my_pkg/Bad")


def test_register_msg_with_unknown_type_leaves_nothing_behind():
    r = MessageRegistry()
    msg = msg_error(r.register_msg, "my_pkg/Bad", "int32 a\nNoSuch thing")
    assert "'my_pkg/Bad'" in msg and "'my_pkg/NoSuch'" in msg
    # the failed class is not half-registered
    assert "unknown message class" in msg_error(r.msg_type, "my_pkg/Bad")
    # and the same name can be registered with a good definition afterwards
    r.register_msg("my_pkg/Bad", "int32 a")
    assert r.bytes_to_json("my_pkg/msg/Bad", r.json_to_bytes("my_pkg/msg/Bad", {"a": 4})) == {"a": 4}


def test_register_conflicting_definition():
    r = MessageRegistry()
    r.register_msg("my_pkg/V", "int32 a")
    r.register_msg("my_pkg/V", "int32 a")           # the same definition again is fine
    assert "'my_pkg/V'" in msg_error(r.register_msg, "my_pkg/V", "int64 a")
    assert r.bytes_to_json("my_pkg/msg/V", r.json_to_bytes("my_pkg/msg/V", {"a": 1})) == {"a": 1}


def make_pkg(root: Path, name: str, msgs: dict[str, str], srvs: dict[str, str]) -> Path:
    d = root / name
    (d / "msg").mkdir(parents=True)
    (d / "srv").mkdir()
    for k, v in msgs.items():
        (d / "msg" / f"{k}.msg").write_text(v)
    for k, v in srvs.items():
        (d / "srv" / f"{k}.srv").write_text(v)
    return d


def test_load_definitions(tmp_path):
    r = MessageRegistry()
    d = make_pkg(tmp_path, "fleet_pkg",
                 {"Goal": "int32 robot\nint32 cell\n", "Status": "Header header\nstring state\n"},
                 {"SetGoal": "Goal goal\n---\nbool ok\nstring reason\n"})
    (d / "msg" / "README.txt").write_text("not a definition")
    names = r.load_definitions("fleet_pkg", d)
    assert names == ["fleet_pkg/Goal", "fleet_pkg/Status", "fleet_pkg/SetGoal"]
    req, resp = r.srv_types("fleet_pkg/SetGoal")
    j = {"goal": {"robot": 1, "cell": 12}}
    assert r.bytes_to_json(req, r.json_to_bytes(req, j)) == j
    assert r.msg_type("fleet_pkg/Status") == "fleet_pkg/msg/Status"


def test_load_definitions_message_refers_to_a_later_file(tmp_path):
    """Path.msg uses Waypoint.msg, which sorts after it."""
    r = MessageRegistry()
    d = make_pkg(tmp_path, "nav_pkg", {"Path": "Waypoint[] points\n", "Waypoint": "float64 x\nfloat64 y\n"}, {})
    assert sorted(r.load_definitions("nav_pkg", d)) == ["nav_pkg/Path", "nav_pkg/Waypoint"]
    t = r.msg_type("nav_pkg/Path")
    j = {"points": [{"x": 1.0, "y": 2.0}]}
    assert r.bytes_to_json(t, r.json_to_bytes(t, j)) == j


def test_load_definitions_without_msg_or_srv_dirs(tmp_path):
    (tmp_path / "empty_pkg").mkdir()
    assert MessageRegistry().load_definitions("empty_pkg", tmp_path / "empty_pkg") == []


@pytest.mark.parametrize("kind, fname, text", [
    ("msg", "Broken", "int32\n"),
    ("msg", "Dangling", "Missing thing\n"),
    ("srv", "NoSep", "int32 a\n"),
    ("srv", "BadHalf", "int32 a\n---\nfloat32[ x\n"),
])
def test_load_definitions_bad_definition_names_the_file(tmp_path, kind, fname, text):
    r = MessageRegistry()
    d = make_pkg(tmp_path, "bad_pkg", {"Good": "int32 a\n"}, {})
    (d / kind / f"{fname}.{kind}").write_text(text)
    msg = msg_error(r.load_definitions, "bad_pkg", d)
    assert str(d / kind / f"{fname}.{kind}") in msg
    assert f"bad_pkg/{fname}" in msg


def test_non_finite_floats_are_null_in_json():
    """JSON has no NaN/Infinity: a LaserScan with inf ranges goes out as null (rosbridge's choice)."""
    import json as _json
    import math as _math
    from rce.messages import MessageRegistry
    reg = MessageRegistry()
    t = reg.msg_type("sensor_msgs/LaserScan")
    data = reg.json_to_bytes(t, {"ranges": [1.0, None], "range_max": 3.5})
    scan = reg.from_json(t, {"ranges": [1.0, 2.0], "range_max": 3.5})
    scan.ranges[1] = float("inf")
    out = reg.to_json(t, scan)
    assert reg.bytes_to_json(t, data)["ranges"] == [1.0, None]
    assert out["ranges"] == [1.0, None]
    _json.loads(_json.dumps(out, allow_nan=False))     # strictly valid JSON
    assert _math.isnan(reg.from_json(t, {"ranges": [None]}).ranges[0])


@pytest.mark.parametrize("cls, field, values, expect", [
    (PWCS, "pose.covariance", [0, 1.5, -2, 1e300] + [0.25] * 32, [0.0, 1.5, -2.0, 1e300] + [0.25] * 32),
    (PWCS, "pose.covariance", [None] + [1] * 35, [None] + [1.0] * 35),          # null reads back as NaN: null
    ("std_msgs/Int32MultiArray", "data", [-2**31, 0, 2**31 - 1], [-2**31, 0, 2**31 - 1]),
    ("std_msgs/Int32MultiArray", "data", [3.0, 4], [3, 4]),                      # an integral float is an integer
    ("std_msgs/Float32MultiArray", "data", [0.5, 2, 1e39], [0.5, 2.0, None]),   # past float32: inf, out as null
])
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")   # numpy's, for the inf above
def test_numeric_arrays_whole_or_item_by_item_agree(reg, cls, field, values, expect):
    """A list of numbers takes the whole-array path or the item-by-item one (a null, an integral
    float): the same values come back either way, as Python numbers of the field's kind."""
    obj: dict = {}
    node = obj
    *outer, last = field.split(".")
    for name in outer:
        node = node.setdefault(name, {})
    node[last] = values
    back = reg.bytes_to_json(reg.msg_type(cls), reg.json_to_bytes(reg.msg_type(cls), obj))
    for name in field.split("."):
        back = back[name]
    assert back == expect
    assert all(type(x) is type(y) for x, y in zip(back, expect, strict=True))
