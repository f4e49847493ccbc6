"""rce.messages.compiled: the compiled ROS 1 codec gives rosbags' bytes and messages, byte for byte,
for every class of the ROS 1 Noetic store (random values, edge cases), and the registry falls back
to the general path with the same result or error wherever the compiled one does not apply."""
from __future__ import annotations

import math
import random
import struct

import numpy as np
import pytest
from rosbags.typesys.base import Nodetype

from rce.messages import JsonForms, MessageRegistry
from rce.messages.compiled import Fallback
from rce.plumbing.errors import MessageError

POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
STRINGS = ["", "map", "base_link", "é漢字 map", "\udcff\udcfe raw bytes", "a" * 300]
_INTS = {"int8": (-128, 127), "uint8": (0, 255), "char": (0, 255), "byte": (0, 127), "int16": (-2**15, 2**15 - 1),
         "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
         "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
_TIMES = {"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"}


def random_json(fielddefs: dict, typename: str, rng: random.Random) -> dict:
    """A JSON-form message of ``typename`` in the canonical forms, with random values (edge values
    often: empty and non-ASCII strings, bytes that are not UTF-8, empty arrays, range limits)."""
    if typename in _TIMES:
        return {"secs": rng.randint(-2**31, 2**31 - 1), "nsecs": rng.randint(0, 999_999_999)}
    if typename == "sensor_msgs/msg/Image":     # an image the PNG form can hold: 1 x 2 rgb8
        return {"header": random_json(fielddefs, "std_msgs/msg/Header", rng), "height": 1, "width": 2,
                "encoding": "rgb8", "is_bigendian": 0, "step": 6, "data": [rng.randint(0, 255) for _ in range(6)]}
    out = {}
    for fname, (nt, arg) in fielddefs[typename][1]:
        if fname == "structure_needs_at_least_one_member":
            continue
        if nt in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            (snt, sarg), length = arg
            n = length if nt == Nodetype.ARRAY else rng.choice([0, 1, 3])
            out[fname] = [value(fielddefs, snt, sarg, rng, array=True) for _ in range(n)]
        else:
            out[fname] = value(fielddefs, nt, arg, rng)
    return out


def value(fielddefs: dict, nt: int, arg, rng: random.Random, array: bool = False):
    if nt == Nodetype.NAME:
        return random_json(fielddefs, arg, rng)
    t = arg[0]
    if t == "string":
        return rng.choice(STRINGS)
    if t == "bool":
        return rng.random() < 0.5
    if t in ("float32", "float64"):
        return rng.choice([0.0, -0.0, 1.5, 1e-300 if t == "float64" else 1e-30, rng.uniform(-1e6, 1e6), math.inf,
                           3])    # an int for a float field is canonical too
    lo, hi = _INTS[t]
    if t == "byte" and array:
        hi = 255
    return rng.choice([lo, hi, rng.randint(lo, hi)])


def same(a, b) -> bool:
    """``a`` and ``b`` are the same message: the same classes, values and array dtypes."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if hasattr(a, "__dataclass_fields__"):
        return all(same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    return a == b


def every_class(reg: MessageRegistry) -> list[str]:
    return sorted(t for t in reg.store.fielddefs if reg.codec(t) is not None)


def test_most_classes_compile_and_empty_ones_do_not(reg):
    assert len(every_class(reg)) > 140
    assert reg.codec("std_msgs/msg/Empty") is None          # rosbags' placeholder field: rosbags does all
    assert reg.codec(POSE).serialize_json is not None
    assert reg.codec("sensor_msgs/msg/Image").serialize_json is None   # images have forms of their own


@pytest.mark.parametrize("seed", range(4))
def test_every_class_round_trips_as_rosbags_does(reg, ts, seed):
    rng = random.Random(seed)
    for t in every_class(reg):
        obj = random_json(reg.store.fielddefs, t, rng)
        msg = reg.from_json(t, obj)
        ref = bytes(ts.serialize_ros1(msg, t))
        codec = reg.codec(t)
        assert codec.serialize(msg) == ref, t
        if codec.serialize_json is not None:
            assert codec.serialize_json(obj, JsonForms()) == ref, t
        assert reg.json_to_bytes(t, obj) == ref, t
        got = codec.deserialize(ref)
        assert same(got, ts.deserialize_ros1(ref, t)), t
        assert codec.serialize(got) == ref, t


@pytest.mark.parametrize("frame_id", ["", "map", "地図", "\udcff"])
def test_pose_edge_cases(reg, ts, frame_id):
    obj = {"header": {"seq": 2**32 - 1, "stamp": {"secs": -1, "nsecs": 999_999_999}, "frame_id": frame_id},
           "pose": {"pose": {"position": {"x": math.nan, "y": -0.0, "z": 1e308},
                             "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                    "covariance": [float(i) for i in range(36)]}}
    ref = bytes(ts.serialize_ros1(reg.from_json(POSE, obj), POSE))
    assert reg.json_to_bytes(POSE, obj) == ref
    assert ref[12:16] == len(frame_id.encode("utf-8", "surrogateescape")).to_bytes(4, "little")
    got = reg.deserialize(POSE, ref)
    assert got.header.frame_id == frame_id
    assert not got.pose.covariance.flags.writeable      # a view of the payload, as rosbags gives it
    assert reg.serialize(POSE, got) == ref


def test_payload_that_does_not_fit_is_refused_naming_the_class(reg, ts):
    good = reg.json_to_bytes(POSE, {})
    for bad in (good[:-1], good + b"\0", good[:10], b"", b"\xff\xff\xff\xff" * 4 + good[16:]):
        with pytest.raises((Fallback, ValueError, struct.error)):     # the compiled function's own errors
            reg.codec(POSE).deserialize(bad)
        with pytest.raises(MessageError, match="PoseWithCovarianceStamped"):
            reg.deserialize(POSE, bad)
    scan = "sensor_msgs/msg/LaserScan"
    data = bytearray(reg.json_to_bytes(scan, {"ranges": [1.0, 2.0]}))
    count = len(data) - 4 - 8 - 4           # ranges' count: before its 2 float32 and the empty intensities
    assert data[count:count + 4] == (2).to_bytes(4, "little")
    data[count:count + 4] = (2**31).to_bytes(4, "little")
    with pytest.raises(MessageError, match="LaserScan"):
        reg.deserialize(scan, bytes(data))


@pytest.mark.parametrize("obj", [
    {},                                                                   # every field left out
    {"header": {"frame_id": "map"}},                                      # seq and stamp left out
    {"header": {"stamp": {"sec": 3, "nanosec": 4}}},                      # the other time form
    {"header": {"stamp": "2024-01-02T03:04:05Z"}},                        # ISO 8601
    {"pose": {"pose": {"position": {"x": None}}}},                        # null float: NaN
    {"header": {"seq": 7.0}},                                             # integral float for an int
    {"pose": {"pose": {"orientation": {"w": 1}}}, "header": {"seq": 1}},  # partly given nested messages
])
def test_other_forms_take_the_general_path_with_its_bytes(reg, ts, obj):
    assert reg.json_to_bytes(POSE, obj) == bytes(ts.serialize_ros1(reg.from_json(POSE, obj), POSE))


@pytest.mark.parametrize("obj, where", [
    ({"header": {"seq": True}}, "header.seq"),
    ({"header": {"seq": -1}}, "header.seq"),
    ({"header": {"frame_id": 3}}, "header.frame_id"),
    ({"pose": {"covariance": [0.0] * 35}}, "pose.covariance"),
    ({"pose": {"pose": {"position": {"x": "1"}}}}, "pose.pose.position.x"),
    ({"pose": {"pose": {"position": {"w": 1.0}}}}, "pose.pose.position.w"),
    ({"extra": 1}, "extra"),
])
def test_bad_input_gets_the_general_paths_error(reg, obj, where):
    with pytest.raises(MessageError, match=where.replace(".", r"\.")):
        reg.json_to_bytes(POSE, obj)


def test_time_form_is_learnt_from_the_canonical_path_too(reg):
    forms = JsonForms(learn=True)
    reg.json_to_bytes(POSE, {"header": {"seq": 1, "stamp": {"secs": 1, "nsecs": 2}, "frame_id": ""}, "pose": {}},
                      forms)
    assert "time" in forms.decided and forms.time == "secs"
    other = JsonForms(learn=True)
    reg.json_to_bytes(POSE, {"header": {"seq": 1, "stamp": {"sec": 1, "nanosec": 2}, "frame_id": ""}}, other)
    assert other.time == "sec"


def test_instance_of_another_shape_takes_rosbags_path(reg, ts):
    t = "std_msgs/msg/Float64MultiArray"
    msg = reg.from_json(t, {"data": [1.0, 2.0]})
    msg.data = msg.data.astype(">f8")                 # big-endian: rosbags swaps it
    assert reg.serialize(t, msg) == bytes(ts.serialize_ros1(msg, t))
    msg.data = [1.0, 2.0]                             # a list: neither path takes it
    with pytest.raises(MessageError, match="Float64MultiArray"):
        reg.serialize(t, msg)


def test_registered_class_with_arrays_of_messages(ts):
    reg = MessageRegistry()
    reg.register_msg("test_pkg/Cell", "int32 index\nstring owner\nfloat32[2] xy")
    reg.register_msg("test_pkg/Grid", "Header header\ntest_pkg/Cell[] cells\ntest_pkg/Cell[2] corners\n"
                                      "string[] names\nbool[] free\nbyte[] raw\nbyte b")
    t = "test_pkg/msg/Grid"
    codec = reg.codec(t)
    assert codec is not None and codec.serialize_json is None      # a byte field: JSON by the general path
    cell = {"index": -5, "owner": "é", "xy": [0.5, -1]}
    obj = {"header": {"frame_id": "grid"}, "cells": [cell, cell], "corners": [cell, cell],
           "names": ["", "\udcff"], "free": [True, False], "raw": [0, 255], "b": 3}
    ref = bytes(reg.store.serialize_ros1(reg.from_json(t, obj), t))
    assert reg.json_to_bytes(t, obj) == ref
    assert codec.serialize(reg.from_json(t, obj)) == ref
    got = reg.deserialize(t, ref)
    assert same(got, reg.store.deserialize_ros1(ref, t))
    assert reg.serialize(t, got) == ref


FORMS = [JsonForms(), JsonForms(time="sec", duration="sec", byte_arrays="binary"),
         JsonForms(time="iso", duration="float"), JsonForms(images="png")]


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize("forms", FORMS, ids=lambda f: "/".join(f.key))
def test_every_class_reads_to_json_as_the_general_path(reg, ts, seed, forms):
    rng = random.Random(seed)
    compiled = 0
    for t in every_class(reg):
        obj = random_json(reg.store.fielddefs, t, rng)
        data = bytes(ts.serialize_ros1(reg.from_json(t, obj), t))
        assert reg.bytes_to_json(t, data, forms) == reg.to_json(t, ts.deserialize_ros1(data, t), forms), t
        compiled += reg._readers.get((t, forms.key)) is not None
    if forms.time in ("secs", "sec"):
        assert compiled > 140


def test_json_reader_edge_values(reg, ts):
    t = "sensor_msgs/msg/LaserScan"
    obj = {"header": {"frame_id": "\udcff laser"}, "ranges": [1.0, math.inf, -math.inf, math.nan, 0.5],
           "intensities": [], "range_max": math.nan}
    data = reg.json_to_bytes(t, obj)
    got = reg.bytes_to_json(t, data)
    assert got == reg.to_json(t, ts.deserialize_ros1(data, t))
    assert got["ranges"] == [1.0, None, None, None, 0.5] and got["range_max"] is None
    assert got["header"]["frame_id"] == "\ufffd laser"
    for bad in (data[:-1], data + b"\0"):
        with pytest.raises(MessageError, match="LaserScan"):
            reg.bytes_to_json(t, bad)
