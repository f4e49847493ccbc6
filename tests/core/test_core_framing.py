"""rce.transport.framing: the one framing of internal links, decoded sans I/O."""
from __future__ import annotations

import json
import struct

import pytest

from rce.transport import framing
from rce.plumbing.errors import ProtocolError
from rce.transport.framing import (CONTROL, DATA, MSG, SRV_ERR, SRV_REQ, SRV_RESP, DataFrame, FrameDecoder, decode_body,
                         encode_control, encode_data, encode_data_header)


def test_control_frame_layout():
    f = encode_control({"op": "x", "n": 1})
    n, kind = struct.unpack("!IB", f[:5])
    assert kind == CONTROL and n == len(f) - 4
    assert json.loads(f[5:]) == {"op": "x", "n": 1}


def test_data_frame_layout():
    f = encode_data(SRV_REQ, 7, 2**64 - 1, 42, b"payload")
    n, kind = struct.unpack("!IB", f[:5])
    assert kind == DATA and n == len(f) - 4 == 1 + 25 + 7
    assert struct.unpack("!BQQQ", f[5:30]) == (SRV_REQ, 7, 2**64 - 1, 42)
    assert f[30:] == b"payload"
    assert encode_data_header(SRV_REQ, 7, 2**64 - 1, 42, 7) + b"payload" == f


def test_ops_are_distinct():
    assert len({MSG, SRV_REQ, SRV_RESP, SRV_ERR}) == 4 and CONTROL != DATA


def test_decoder_whole_frames_in_one_feed():
    d = FrameDecoder()
    out = d.feed(encode_control({"a": 1}) + encode_data(MSG, 1, 2, 0, b"xyz") + encode_control({"b": [2]}))
    assert out[0] == {"a": 1} and out[2] == {"b": [2]}
    df = out[1]
    assert isinstance(df, DataFrame) and (df.op, df.dst, df.src, df.call_id) == (MSG, 1, 2, 0)
    assert bytes(df.payload) == b"xyz"


def test_decoder_byte_by_byte():
    stream = (encode_control({"op": "hello", "text": "ü" * 3}) + encode_data(SRV_RESP, 3, 4, 99, b"\x00" * 300)
              + encode_data(MSG, 5, 6, 0, b"") + encode_control({}))
    d = FrameDecoder()
    out = []
    counts = []
    for i in range(len(stream)):
        got = d.feed(stream[i:i + 1])
        out += got
        counts.append(len(got))
    assert len(out) == 4 and sum(counts) == 4 and max(counts) == 1
    assert out[0] == {"op": "hello", "text": "üüü"} and out[3] == {}
    assert (out[1].op, out[1].dst, out[1].src, out[1].call_id) == (SRV_RESP, 3, 4, 99)
    assert bytes(out[1].payload) == b"\x00" * 300
    assert bytes(out[2].payload) == b"" and out[2].dst == 5
    # nothing is left over
    assert d.feed(b"") == []


@pytest.mark.parametrize("cut", [1, 3, 4, 5, 6, 20, 31])
def test_decoder_split_anywhere(cut):
    f = encode_data(SRV_ERR, 1, 1, 1, b"reason") + encode_control({"k": "v"})
    d = FrameDecoder()
    first = d.feed(f[:cut])
    rest = d.feed(f[cut:])
    out = first + rest
    assert [type(x).__name__ for x in out] == ["DataFrame", "dict"]
    assert bytes(out[0].payload) == b"reason" and out[1] == {"k": "v"}


def test_decoder_oversized_frame_refused_from_the_header_alone():
    d = FrameDecoder(max_frame=100)
    assert len(d.feed(encode_control({"x": "a" * 80}))) == 1          # under the limit
    with pytest.raises(ProtocolError) as ei:
        d.feed(struct.pack("!IB", 102, CONTROL))                       # body of 101 bytes announced
    assert "101 bytes" in ei.value.message and "100" in ei.value.message


def test_decoder_frame_exactly_at_limit():
    body = json.dumps({"x": "a" * 50}).encode()
    d = FrameDecoder(max_frame=len(body))
    assert d.feed(struct.pack("!IB", len(body) + 1, CONTROL) + body) == [{"x": "a" * 50}]


@pytest.mark.parametrize("body, what", [
    (b"{not json", "not valid JSON"),
    (b"\xff\xfe", "not valid JSON"),
    (b"[1,2]", "JSON object"),
    (b"3", "JSON object"),
])
def test_decoder_bad_control_body(body, what):
    with pytest.raises(ProtocolError) as ei:
        FrameDecoder().feed(struct.pack("!IB", len(body) + 1, CONTROL) + body)
    assert what in ei.value.message


def test_decoder_short_data_frame():
    with pytest.raises(ProtocolError) as ei:
        FrameDecoder().feed(struct.pack("!IB", 1 + 10, DATA) + b"\x00" * 10)
    assert "shorter than its header" in ei.value.message


@pytest.mark.parametrize("kind", [0, 3, 255])
def test_decoder_unknown_kind(kind):
    with pytest.raises(ProtocolError) as ei:
        FrameDecoder().feed(struct.pack("!IB", 3, kind) + b"{}")
    assert f"unknown frame kind {kind}" in ei.value.message


def test_decoder_zero_length_frame():
    """A length of 0 cannot even hold the kind byte."""
    with pytest.raises(ProtocolError):
        FrameDecoder().feed(b"\x00\x00\x00\x00" + encode_control({"next": 1}))


def test_decode_body_directly():
    assert decode_body(CONTROL, b'{"a":1}') == {"a": 1}
    df = decode_body(DATA, struct.pack("!BQQQ", MSG, 1, 2, 3) + b"p")
    assert (df.op, df.dst, df.src, df.call_id, bytes(df.payload)) == (MSG, 1, 2, 3, b"p")
    assert isinstance(df.payload, memoryview)


def test_default_max_frame():
    assert FrameDecoder().max_frame == framing.DEFAULT_MAX_FRAME == 64 * 1024 * 1024


def test_decoder_yields_the_frames_before_a_bad_one():
    """A link dispatches every good frame that arrived before a bad one, then closes."""
    d = FrameDecoder()
    gen = d.frames(encode_control({"a": 1}) + encode_data(MSG, 9, 8, 7, b"zz") + struct.pack("!IB", 1, 9))
    assert next(gen) == {"a": 1}
    df = next(gen)
    assert (df.dst, df.src, df.call_id, bytes(df.payload)) == (9, 8, 7, b"zz")
    with pytest.raises(ProtocolError) as ei:
        next(gen)
    assert "unknown frame kind 9" in ei.value.message


def test_decoder_large_frame_in_many_pieces():
    payload = bytes(range(256)) * 4096                       # 1 MiB
    stream = encode_data(MSG, 1, 2, 3, payload) + encode_control({"after": True})
    d = FrameDecoder()
    out = []
    for i in range(0, len(stream), 65536):
        out += d.feed(stream[i:i + 65536])
    assert len(out) == 2 and bytes(out[0].payload) == payload and out[1] == {"after": True}


def test_decoder_payload_is_a_view_of_the_chunk():
    chunk = encode_data(MSG, 1, 2, 3, b"abc")
    (df,) = FrameDecoder().feed(chunk)
    assert isinstance(df.payload, memoryview) and df.payload.obj is chunk


# -- the buffered-protocol way in (rce.transport.link's transport receives straight into the decoder) ----------

def _receive(d: FrameDecoder, stream: bytes, read: int) -> list:
    """Feed ``stream`` as a transport would: into :meth:`get_buffer`, at most ``read`` bytes a time."""
    out, pos = [], 0
    while pos < len(stream):
        buf = d.get_buffer()
        k = min(len(buf), read, len(stream) - pos)
        buf[:k] = stream[pos:pos + k]
        pos += k
        out += d.buffer_updated(k)
    return out


@pytest.mark.parametrize("read", [1, 7, 4096, 300_000, 10**7])
def test_buffered_frames_split_across_reads(read):
    big = bytes(range(256)) * 2000                               # 512000 bytes: larger than a chunk
    stream = (encode_control({"a": 1}) + encode_data(MSG, 1, 2, 3, big) + encode_data(MSG, 4, 5, 6, b"s")
              + encode_data(SRV_RESP, 7, 8, 9, big[:1000]) + encode_control({"b": 2}))
    out = _receive(FrameDecoder(chunk=4096), stream, read)
    assert out[0] == {"a": 1} and out[4] == {"b": 2}
    assert [(f.op, f.dst, f.src, f.call_id) for f in out[1:4]] == [(MSG, 1, 2, 3), (MSG, 4, 5, 6), (SRV_RESP, 7, 8, 9)]
    assert bytes(out[1].payload) == big and bytes(out[2].payload) == b"s" and bytes(out[3].payload) == big[:1000]


def test_buffered_large_payload_is_a_view_of_its_own_buffer_and_is_not_reused_while_held():
    """A large frame's payload is a view (no copy) of a buffer bigger than itself; its buffer is
    reused for a later frame only once nobody holds a view of it."""
    d = FrameDecoder(chunk=1024)
    first, second = b"1" * 5000, b"2" * 3000
    (f1,) = _receive(d, encode_data(MSG, 1, 1, 1, first), 10**6)
    assert isinstance(f1.payload, memoryview) and len(f1.payload.obj) >= 5000 + 29
    (f2,) = _receive(d, encode_data(MSG, 2, 2, 2, second), 10**6)
    assert bytes(f1.payload) == first and bytes(f2.payload) == second      # held: not overwritten
    assert f2.payload.obj is not f1.payload.obj
    earlier = {id(f1.payload.obj), id(f2.payload.obj)}
    del f1, f2
    (f3,) = _receive(d, encode_data(MSG, 3, 3, 3, second), 10**6)
    assert bytes(f3.payload) == second and id(f3.payload.obj) in earlier   # let go of: reused, no fresh pages


def test_buffered_small_frames_outlive_the_next_read():
    """Small frames are copied out of the receive buffer once: the next read does not change them."""
    d = FrameDecoder(chunk=64)
    (f1,) = _receive(d, encode_data(MSG, 1, 1, 1, b"abc"), 64)
    _receive(d, encode_data(MSG, 1, 1, 1, b"xyz"), 64)
    assert bytes(f1.payload) == b"abc"


def test_buffered_oversized_frame_refused_from_its_header_before_any_buffer():
    d = FrameDecoder(max_frame=100, chunk=64)
    good = _receive(d, encode_control({"x": 1}), 64)
    with pytest.raises(ProtocolError, match="exceeds the limit of 100 bytes"):
        _receive(d, struct.pack("!IB", 10**6, DATA), 64)
    assert good == [{"x": 1}] and d._big is None and not d._spares


def test_buffered_and_chunk_feeding_mix():
    """A frame begun through :meth:`feed` is finished through the buffer, and the other way."""
    payload = b"p" * 3000
    stream = encode_data(MSG, 1, 2, 3, payload) * 2
    d = FrameDecoder(chunk=1024)
    out = d.feed(stream[:100]) + _receive(d, stream[100:4000], 333) + d.feed(stream[4000:])
    assert [bytes(f.payload) for f in out] == [payload, payload]
