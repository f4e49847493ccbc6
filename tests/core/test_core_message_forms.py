"""The original RCE's message forms, both ways (rce.messages.forms, rce.messages, rce.messages.structure):
time as ISO 8601 and duration as float seconds, images as PNG/JPEG binary parts, uint8[] as binary
parts, each client answered in the form it used; forwarded bytes checked without decoding; and
containerData's ``size`` (a size class) apart from ``pids`` (the task limit)."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from rce.messages import forms as message_forms
from rce.plumbing.errors import MessageError
from rce.messages.forms import RCE_FORMS, JsonForms, image_to_bytes, iso_to_time, time_to_iso
from rce.messages import MessageRegistry, takes_binary_message
from rce.protocol.frames import Assembler, encode
from rce.protocol.schema import validate

HEADER, DURATION, IMAGE = "std_msgs/msg/Header", "std_msgs/msg/Duration", "sensor_msgs/msg/Image"
T0 = 1378123200          # 2013-09-02T12:00:00 UTC: rce-comm 20130902's release day


@pytest.fixture(scope="module")
def reg() -> MessageRegistry:
    return MessageRegistry()


def msg_error(fn, *args) -> str:
    with pytest.raises(MessageError) as ei:
        fn(*args)
    return ei.value.message


def png(pixels: np.ndarray, mode: str | None = None, fmt: str = "PNG", **save) -> bytes:
    out = io.BytesIO()
    (Image.fromarray(pixels, mode) if mode else Image.fromarray(pixels)).save(out, fmt, **save)
    return out.getvalue()


def pixels_of(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)))


# -- time and duration -------------------------------------------------------------------------------------
def test_the_originals_time_and_duration_forms_exactly():
    # rce-core/rce/util/converter.py: datetime.fromtimestamp(t.to_sec()).isoformat() (a UTC host), Duration.to_sec()
    assert time_to_iso(T0, 500_000_000) == "2013-09-02T12:00:00.500000"
    assert time_to_iso(T0, 0) == "2013-09-02T12:00:00.000000"       # six digits always: the original parser needs them
    assert time_to_iso(0, 999) == "1970-01-01T00:00:00.000000"      # microseconds, truncated
    assert message_forms.duration_to_seconds(1, 500_000_000) == 1.5
    assert message_forms.duration_to_seconds(-1, 750_000_000) == -0.25


@pytest.mark.parametrize("text, expected", [
    ("2013-09-02T12:00:00.500000", (T0, 500_000_000)),
    ("2013-09-02T12:00:00", (T0, 0)),
    ("2013-09-02 12:00:00.5", (T0, 500_000_000)),
    ("2013-09-02T12:00:00.123456789Z", (T0, 123_456_789)),
    ("2013-09-02T14:00:00.000001+02:00", (T0, 1000)),             # the original dropped the zone; it is kept here
    ("2013-09-02T07:30:00-0430", (T0, 0)),
    ("1970-01-01T00:00:00Z", (0, 0)),
])
def test_iso_8601_times_in(text, expected):
    assert iso_to_time(text) == expected


@pytest.mark.parametrize("text, why", [
    ("yesterday", "not an ISO 8601 time"), ("2013-13-02T12:00:00", "month must be in 1..12"),
    ("2013-09-02T12:00:00.1234567890", "not an ISO 8601 time"), ("1969-12-31T23:59:59", "before 1970"),
])
def test_bad_iso_8601_times(text, why):
    with pytest.raises(ValueError, match=why):
        iso_to_time(text)


def test_a_time_in_any_form_is_the_same_message(reg):
    forms = [{"secs": T0, "nsecs": 500_000_000}, {"sec": T0, "nanosec": 500_000_000}, "2013-09-02T12:00:00.500000",
             "2013-09-02T12:00:00.5+00:00"]
    out = {reg.json_to_bytes(HEADER, {"seq": 7, "stamp": s, "frame_id": "map"}) for s in forms}
    assert len(out) == 1
    assert reg.bytes_to_json(HEADER, out.pop())["stamp"] == {"secs": T0, "nsecs": 500_000_000}   # rce's by default


def test_a_duration_in_any_form_is_the_same_message(reg):
    out = {reg.json_to_bytes(DURATION, {"data": d}) for d in
           (1.5, "1.5", {"secs": 1, "nsecs": 500_000_000}, {"sec": 1, "nanosec": 500_000_000})}
    assert len(out) == 1
    neg = reg.json_to_bytes(DURATION, {"data": -0.25})
    assert reg.bytes_to_json(DURATION, neg) == {"data": {"secs": -1, "nsecs": 750_000_000}}


@pytest.mark.parametrize("cls, obj, parts", [
    (HEADER, {"stamp": "soon"}, ["std_msgs/Header: field 'stamp'", "'soon' is not an ISO 8601 time"]),
    (HEADER, {"stamp": 12.5}, ["field 'stamp' must be an object {secs, nsecs} or an ISO 8601 string, got float"]),
    (HEADER, {"stamp": "2100-01-01T00:00:00"}, ["field 'stamp'", "out of range for int32"]),
    (DURATION, {"data": "long"}, ["std_msgs/Duration: field 'data'", "'long' is not a number of seconds"]),
    (DURATION, {"data": None}, ["field 'data'", "not a number of seconds"]),
    (DURATION, {"data": float("inf")}, ["field 'data'", "not a finite number"]),
    (DURATION, {"data": True}, ["field 'data'", "not a number of seconds"]),
    (DURATION, {"data": [1]}, ["field 'data' must be an object {secs, nsecs} or seconds (a number), got list"]),
])
def test_bad_times_and_durations_name_the_field(reg, cls, obj, parts):
    msg = msg_error(reg.json_to_bytes, cls, obj)
    for p in parts:
        assert p in msg, (p, msg)


def test_each_client_gets_back_the_time_form_it_used(reg):
    data = reg.json_to_bytes(HEADER, {"stamp": {"secs": T0, "nsecs": 500_000_000}})
    dur = reg.json_to_bytes(DURATION, {"data": 1.5})
    original = JsonForms(learn=True)
    reg.json_to_bytes(HEADER, {"frame_id": "no stamp"}, original)          # a missing stamp decides nothing
    assert original.key == RCE_FORMS.key
    reg.json_to_bytes(HEADER, {"stamp": "2013-09-02T12:00:00.000000"}, original)
    assert reg.bytes_to_json(HEADER, data, original)["stamp"] == "2013-09-02T12:00:00.500000"
    assert reg.bytes_to_json(DURATION, dur, original) == {"data": 1.5}    # the family: ISO time, float duration
    reg.json_to_bytes(HEADER, {"stamp": {"secs": 1, "nsecs": 0}}, original)  # the first one decided
    assert reg.bytes_to_json(HEADER, data, original)["stamp"] == "2013-09-02T12:00:00.500000"

    by_duration = JsonForms(learn=True)
    reg.json_to_bytes(DURATION, {"data": 2}, by_duration)
    assert (by_duration.time, by_duration.duration) == ("iso", "float")
    ros2 = JsonForms(learn=True)
    reg.json_to_bytes(HEADER, {"stamp": {"sec": 1, "nanosec": 2}}, ros2)
    assert reg.bytes_to_json(HEADER, data, ros2)["stamp"] == {"sec": T0, "nanosec": 500_000_000}
    assert reg.bytes_to_json(DURATION, dur, ros2) == {"data": {"sec": 1, "nanosec": 500_000_000}}
    rce = JsonForms(learn=True)
    reg.json_to_bytes(HEADER, {"stamp": {"secs": 1, "nsecs": 2}}, rce)
    reg.json_to_bytes(HEADER, {"stamp": "2013-09-02T12:00:00"}, rce)
    assert reg.bytes_to_json(HEADER, data, rce)["stamp"] == {"secs": T0, "nsecs": 500_000_000}
    # without learn (and for callers that pass none) nothing changes
    fixed = JsonForms()
    reg.json_to_bytes(HEADER, {"stamp": "2013-09-02T12:00:00"}, fixed)
    reg.json_to_bytes(HEADER, {"stamp": "2013-09-02T12:00:00"})
    assert fixed.key == RCE_FORMS.key == ("secs", "secs", "json", "base64")
    assert json.loads(json.dumps(reg.bytes_to_json(HEADER, data, original), allow_nan=False))


def test_forms_are_checked():
    with pytest.raises(ValueError, match="JSON form time='unix'"):
        JsonForms(time="unix")
    assert JsonForms(time="iso", duration="float", images="jpeg", byte_arrays="binary").key == \
        ("iso", "float", "jpeg", "binary")


# -- images and byte arrays as binary parts ----------------------------------------------------------------
GREY = (np.arange(12, dtype=np.uint8).reshape(3, 4) * 20)
RGB = np.stack([GREY, 255 - GREY, GREY // 2], axis=-1)


def test_a_png_binary_part_is_a_sensor_msgs_image_both_ways(reg):
    forms = JsonForms(learn=True)
    raw = reg.json_to_bytes(IMAGE, png(GREY), forms)                    # what the original's client sent as msg*
    msg = reg.deserialize(IMAGE, raw)
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step) == (3, 4, "mono8", 0, 4)
    assert bytes(msg.data) == GREY.tobytes() and msg.header.frame_id == ""
    assert forms.images == "png"
    back = reg.bytes_to_json(IMAGE, raw, forms)
    assert back[:8] == b"\x89PNG\r\n\x1a\n" and (pixels_of(back) == GREY).all()
    assert reg.bytes_to_json(IMAGE, raw)["encoding"] == "mono8"         # rce's clients keep getting objects
    # on the wire: the whole message is one binary part msg*, and comes back as bytes
    text, frames = encode({"type": "DM", "data": {"iTag": "cam", "type": "sensor_msgs/Image", "msgID": "",
                                                  "msg": back}})
    assert json.loads(text)["data"]["msg*"] == frames[0][:32].decode()
    asm = Assembler()
    assert asm.feed_text(text, 0.0) == [] and asm.feed_binary(frames[0], 0.0)[0]["data"]["msg"] == back
    assert takes_binary_message("sensor_msgs/Image") and not takes_binary_message("std_msgs/String")
    assert not takes_binary_message("not a class")


@pytest.mark.parametrize("pixels, mode, encoding, expect", [
    (RGB, None, "rgb8", RGB),
    (np.dstack([RGB, np.full((3, 4), 128, np.uint8)]), None, "rgba8", None),
    (GREY.astype(np.uint16) * 250, None, "mono16", None),
    (GREY // 20, "P", "rgb8", None),                     # a palette image: RGB, as the original converted it
    (GREY > 100, None, "mono8", (GREY > 100).astype(np.uint8) * 255),
])
def test_png_modes(reg, pixels, mode, encoding, expect):
    msg = reg.from_json(IMAGE, png(pixels, mode))
    assert msg.encoding == encoding and (msg.height, msg.width) == (3, 4)
    if expect is not None:
        assert bytes(msg.data) == np.ascontiguousarray(expect).tobytes()
    again = reg.from_json(IMAGE, image_to_bytes(msg, "png"))          # lossless both ways
    assert again.encoding == encoding and bytes(again.data) == bytes(msg.data)


def test_jpeg_in_and_out(reg):
    forms = JsonForms(learn=True)
    flat = np.full((8, 16, 3), (200, 100, 50), np.uint8)          # JPEG is lossy: a flat colour keeps
    msg = reg.from_json(IMAGE, png(flat, fmt="JPEG", quality=95), forms)
    assert forms.images == "jpeg" and msg.encoding == "rgb8" and (msg.height, msg.width, msg.step) == (8, 16, 48)
    assert np.abs(np.asarray(msg.data, dtype=int) - flat.reshape(-1)).max() < 8
    out = reg.to_json(IMAGE, msg, forms)
    assert out[:2] == b"\xff\xd8" and np.abs(pixels_of(out).astype(int) - flat).max() < 8
    rgba = reg.from_json(IMAGE, png(np.dstack([RGB, RGB[:, :, :1]])))
    assert "has no JPEG form" in msg_error(reg.to_json, IMAGE, rgba, forms)


def test_bgr8_and_padded_rows_go_out_as_the_right_pixels(reg):
    bgr = RGB[:, :, ::-1]
    padded = np.zeros((3, 16), np.uint8)
    padded[:, :12] = bgr.reshape(3, 12)
    msg = reg.from_json(IMAGE, {"height": 3, "width": 4, "encoding": "bgr8", "step": 16,
                                "data": padded.tobytes()})
    assert (pixels_of(image_to_bytes(msg, "png")) == RGB).all()


def test_image_errors_name_the_field(reg):
    assert "not a PNG or JPEG image" in msg_error(reg.json_to_bytes, IMAGE, b"no image at all")
    assert "only PNG and JPEG" in msg_error(reg.json_to_bytes, IMAGE, png(GREY, fmt="GIF"))
    depth = reg.from_json(IMAGE, {"height": 1, "width": 1, "encoding": "32FC1", "step": 4, "data": [0, 0, 0, 0]})
    assert "sensor_msgs/Image: encoding '32FC1' has no PNG form" in msg_error(
        reg.to_json, IMAGE, depth, JsonForms(images="png"))
    short = reg.from_json(IMAGE, {"height": 2, "width": 2, "encoding": "mono8", "step": 2, "data": [1, 2, 3]})
    assert "3 bytes of data do not hold 2 rows" in msg_error(reg.to_json, IMAGE, short, JsonForms(images="png"))
    # a whole message as bytes is for images only
    assert "message must be a JSON object, got bytes" in msg_error(reg.json_to_bytes, "std_msgs/msg/String", b"x")


def test_an_image_too_large_is_refused_before_it_is_decoded(reg, monkeypatch):
    monkeypatch.setattr(message_forms, "IMAGE_MAX_PIXELS", 11)
    assert "a 4x3 image is larger than 11 pixels" in msg_error(reg.json_to_bytes, IMAGE, png(GREY))


def test_a_nested_image_travels_as_its_own_binary_part(reg):
    t = "stereo_msgs/msg/DisparityImage"
    forms = JsonForms(learn=True)
    raw = reg.json_to_bytes(t, {"image": png(GREY), "f": 2.0, "T": 0.1}, forms)
    assert reg.deserialize(t, raw).image.encoding == "mono8"
    out = reg.bytes_to_json(t, raw, forms)
    assert isinstance(out["image"], bytes) and out["f"] == 2.0
    text, frames = encode(out)
    assert "image*" in json.loads(text) and len(frames) == 1
    assert "field 'image'" in msg_error(reg.json_to_bytes, t, {"image": b"junk"})


def test_uint8_arrays_as_binary_parts_both_ways(reg):
    forms = JsonForms(learn=True)
    j = {"height": 1, "width": 3, "encoding": "mono8", "step": 3, "data": b"\x00\x7f\xff"}
    raw = reg.json_to_bytes(IMAGE, j, forms)
    assert forms.byte_arrays == "binary" and forms.images == "json"
    out = reg.bytes_to_json(IMAGE, raw, forms)
    assert out["data"] == b"\x00\x7f\xff" and reg.bytes_to_json(IMAGE, raw)["data"] == "AH//"
    text, frames = encode({"msg": out})
    assert list(json.loads(text)["msg"])[-1] == "data*" and frames[0][32:] == b"\x00\x7f\xff"
    b64 = JsonForms(learn=True)
    reg.json_to_bytes(IMAGE, {"data": "AH//"}, b64)
    reg.json_to_bytes(IMAGE, {"data": b"\x01"}, b64)                    # the first one decided
    assert b64.byte_arrays == "base64"
    fixed = MessageRegistry()
    fixed.register_msg("test_msgs/Id", "uint8[16] uuid")
    assert "must have 16 items, got 2" in msg_error(fixed.json_to_bytes, "test_msgs/msg/Id", {"uuid": b"ab"})
    uuid = bytes(range(16))
    assert fixed.bytes_to_json("test_msgs/msg/Id", fixed.json_to_bytes("test_msgs/msg/Id", {"uuid": uuid}),
                               JsonForms(byte_arrays="binary")) == {"uuid": uuid}


# -- forwarders: the structure, not the strings ------------------------------------------------------------
def test_a_string_that_is_not_utf8_passes_a_forwarder_and_a_node_and_converts_with_replacements(reg):
    payload = b"\x04\x00\x00\x00\xff\xfe\x00\x80"
    reg.check_structure("std_msgs/msg/String", payload)                 # a forwarder: passes untouched
    msg = reg.deserialize("std_msgs/msg/String", payload)               # a node: the same bytes come back
    assert reg.serialize("std_msgs/msg/String", msg) == payload
    assert reg.bytes_to_json("std_msgs/msg/String", payload) == {"data": "\ufffd\ufffd\x00\ufffd"}   # a converter


@pytest.mark.parametrize("cls, obj, cut, parts", [
    ("std_msgs/msg/String", {"data": "abc"}, -1, ["6 bytes do not fit std_msgs/String: field 'data'", "counts 3"]),
    ("std_msgs/msg/String", {"data": "abc"}, 2, ["field 'data' needs a 4-byte length at offset 0, 2 byte(s) left"]),
    ("geometry_msgs/msg/PoseStamped", {}, 10, ["field 'header.stamp' needs 8 byte(s) at offset 4, 6 left"]),
    ("geometry_msgs/msg/PoseStamped", {"header": {"frame_id": "map"}}, 30, ["field 'pose' needs 56 byte(s)"]),
    ("sensor_msgs/msg/PointCloud2", {"fields": [{"name": "x"}, {"name": "intensity"}]}, 54,
     ["field 'fields[1].name' counts 9 item(s) of 1+ byte(s) at offset 42, 8 byte(s) left"]),
    ("sensor_msgs/msg/LaserScan", {"ranges": [1.0, 2.0]}, -1, ["field 'intensities'"]),
])
def test_forwarded_bytes_that_do_not_fit_name_the_field(reg, cls, obj, cut, parts):
    msg = msg_error(reg.check_structure, cls, reg.json_to_bytes(cls, obj)[:cut])
    for p in parts:
        assert p in msg, (p, msg)


def test_trailing_bytes_and_absurd_counts(reg):
    t = "sensor_msgs/msg/LaserScan"
    data = reg.json_to_bytes(t, {"ranges": [1.0]})
    assert "1 byte(s) left after the last field" in msg_error(reg.check_structure, t, data + b"\x00")
    huge = b"\x00" * 4 + b"\x00" * 8 + b"\xff\xff\xff\xff"                # frame_id of 4 GiB in a 16-byte payload
    assert "field 'header.frame_id' counts 4294967295 item(s)" in msg_error(reg.check_structure, t, huge)
    arr = "geometry_msgs/msg/PoseArray"
    many = reg.json_to_bytes(arr, {})[:-4] + b"\xff\xff\xff\x7f"
    assert "field 'poses' counts 2147483647 item(s) of 56+ byte(s)" in msg_error(reg.check_structure, arr, many)


def test_every_noetic_message_fits_itself_and_not_one_byte_less(reg):
    for t in sorted(reg.store.fielddefs):
        data = reg.json_to_bytes(t, {})
        reg.check_structure(t, data)
        if data:
            with pytest.raises(MessageError, match="do not fit"):
                reg.check_structure(t, data[:-1])


# -- containerData: size is a size class, pids the task limit ----------------------------------------------
def test_container_data_size_and_pids():
    t, data = validate({"type": "CC", "data": {"containerTag": "c", "containerData": {"size": 1, "pids": 64}}})
    assert data.wire()["containerData"] == {"size": 1, "pids": 64} and data.containerData.pids == 64
    with pytest.raises(Exception, match="containerData.pids"):
        validate({"type": "CC", "data": {"containerTag": "c", "containerData": {"pids": -1}}})
