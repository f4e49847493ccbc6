"""The one framing for internal links (control plane, data plane, container bus).

A frame is ``u32 length | u8 kind | body`` (big-endian; ``length`` counts kind and
body). ``kind`` is :data:`CONTROL` (UTF-8 JSON object) or :data:`DATA`. A DATA
body is ``u8 op | u64 dst | u64 src | u64 call_id | payload`` where ``dst`` and
``src`` are interface (or bus handle) ids and ``payload`` is a ROS 1 serialized
message, carried as opaque bytes: no JSON and no re-encoding on internal hops.
"""
from __future__ import annotations

import json
import mmap
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass

from rce.plumbing.errors import ProtocolError

CONTROL = 1
DATA = 2

# DATA ops
MSG = 1        # topic message
SRV_REQ = 2    # service request
SRV_RESP = 3   # service response
SRV_ERR = 4    # service failure; payload is a UTF-8 reason

_HEAD = struct.Struct("!IB")
_DATA = struct.Struct("!BQQQ")
DEFAULT_MAX_FRAME = 64 * 1024 * 1024   # bytes
# bytes of a decoder's buffer for small frames; a larger frame is received into a buffer of its own
READ_CHUNK = 256 * 1024
# large-frame buffers a decoder keeps for reuse once nobody holds a view of them (fresh pages cost a
# page fault each: on this VM a fresh 10 MB buffer costs ~25 ms, a reused one ~4 ms to fill)
SPARE_BUFFERS = 2
SPARE_MAX = 32 * 1024 * 1024      # bytes: a larger buffer is used once and let go


@dataclass(slots=True)
class DataFrame:
    """A decoded DATA frame. ``payload`` is a memoryview slice of the received bytes (no copy)."""
    op: int
    dst: int
    src: int
    call_id: int
    payload: bytes | memoryview


def encode_control(obj: dict) -> bytes:
    """Frame a control message (JSON object)."""
    body = json.dumps(obj, separators=(",", ":")).encode()
    return _HEAD.pack(len(body) + 1, CONTROL) + body


def encode_data_header(op: int, dst: int, src: int, call_id: int, payload_len: int) -> bytes:
    """Header bytes of a DATA frame whose payload (``payload_len`` bytes) is written after it.
    Writing header and payload separately avoids copying large payloads."""
    return _HEAD.pack(1 + _DATA.size + payload_len, DATA) + _DATA.pack(op, dst, src, call_id)


DATA_HEADER_LEN = _HEAD.size + _DATA.size     # bytes of encode_data_header's header


def data_pair(header: bytes | memoryview) -> tuple[int, int] | None:
    """``(src, dst)`` of the DATA frame whose header (its first :data:`DATA_HEADER_LEN` bytes, or
    more) is ``header``; None for any other frame."""
    if len(header) < DATA_HEADER_LEN or header[4] != DATA:
        return None
    _op, dst, src, _cid = _DATA.unpack_from(header, _HEAD.size)
    return src, dst


def encode_data(op: int, dst: int, src: int, call_id: int, payload: bytes) -> bytes:
    """Frame a DATA message in one buffer (convenient for small payloads)."""
    return encode_data_header(op, dst, src, call_id, len(payload)) + payload


def decode_body(kind: int, body: bytes | memoryview) -> dict | DataFrame:
    """Decode a frame body by ``kind``; raises :class:`ProtocolError` on malformed input.
    A DATA frame's payload is a view of ``body`` (no copy)."""
    if kind == CONTROL:
        try:
            obj = json.loads(body if isinstance(body, (bytes, bytearray)) else bytes(body))
        except (ValueError, UnicodeDecodeError) as e:
            raise ProtocolError(f"control frame is not valid JSON: {e}") from None
        if not isinstance(obj, dict):
            raise ProtocolError("control frame must be a JSON object")
        return obj
    if kind == DATA:
        if len(body) < _DATA.size:
            raise ProtocolError(f"data frame of {len(body)} bytes is shorter than its header")
        op, dst, src, call_id = _DATA.unpack_from(body)
        return DataFrame(op, dst, src, call_id, memoryview(body)[_DATA.size:])
    raise ProtocolError(f"unknown frame kind {kind}")


def _check_length(length: int, max_frame: int) -> None:
    if length < 1:
        raise ProtocolError("frame length 0 leaves no room for its kind byte")
    if length - 1 > max_frame:
        raise ProtocolError(f"frame of {length - 1} bytes exceeds the limit of {max_frame} bytes")


def _scan(buf: bytes | bytearray | memoryview, pos: int, end: int, max_frame: int) -> tuple[int, ProtocolError | None]:
    """Where the whole frames in ``buf[pos:end]`` end, and the error of the first bad frame header
    (checked as soon as its 5 bytes are in, whole or not) or None."""
    while end - pos >= _HEAD.size:
        n = _HEAD.unpack_from(buf, pos)[0]
        try:
            _check_length(n, max_frame)
        except ProtocolError as e:
            return pos, e
        if end - pos < 4 + n:
            break
        pos += 4 + n
    return pos, None


def _decode_whole(view: memoryview, pos: int, stop: int) -> Iterator[dict | DataFrame]:
    """Decode the whole frames ``view[pos:stop]`` in place (DATA payloads are views of ``view``)."""
    while pos < stop:
        n, kind = _HEAD.unpack_from(view, pos)
        yield decode_body(kind, view[pos + _HEAD.size:pos + 4 + n])
        pos += 4 + n


class FrameDecoder:
    """Sans-I/O incremental decoder: bytes in (as they arrive from a stream), frames out.

    Two ways in, one state (mixing them is fine):

    - :meth:`frames` (or :meth:`feed`, a list) takes a chunk of immutable ``bytes``: its whole
      frames are decoded in place (a DATA payload is a view of the chunk), the rest is kept.
    - :meth:`get_buffer` / :meth:`buffer_updated` are for :class:`asyncio.BufferedProtocol`: the
      transport receives straight into the buffer lent. Small frames gather in a buffer of
      ``chunk`` bytes and are copied out once, as ``bytes``, when whole; a frame larger than
      ``chunk`` gets a buffer of its own (anonymous ``mmap``, sized from its header, its pages
      filled only as bytes arrive), into which the rest of it is received: no copy at all.

    Either way a DATA payload is a view of bytes that are never written again: it stays valid
    after the frame was handled (a subscriber's queue may keep it). Frames come out in order,
    a frame before a bad one still delivered.

    Raises :class:`ProtocolError` for a frame that announces more than ``max_frame`` bytes (as
    soon as its header is in) or is malformed; the stream is then out of step and the decoder
    must not be fed again."""

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME, chunk: int = READ_CHUNK):
        self.max_frame = max_frame
        self._buf = bytearray(chunk)      # the start of an incomplete frame, then what arrives after it
        self._end = 0                     # bytes in _buf
        self._big: memoryview | None = None   # a frame larger than _buf, being received into its own buffer
        self._have = 0                    # bytes of _big received
        self._spares: list[mmap.mmap] = []   # buffers of earlier large frames, reused when no view is left

    def feed(self, data: bytes) -> list[dict | DataFrame]:
        """Every frame completed by ``data``, in order."""
        return list(self.frames(data))

    def frames(self, data: bytes) -> Iterator[dict | DataFrame]:
        """Yield every frame completed by ``data`` (immutable bytes), in order."""
        view = memoryview(data)
        pos, end = 0, len(view)
        while pos < end:
            if self._big is None and not self._end:       # nothing kept: whole frames decoded in place
                stop, error = _scan(view, pos, end, self.max_frame)
                yield from _decode_whole(view, pos, stop)
                if error is not None:
                    raise error
                pos = stop
                if pos == end:
                    return
            room = self.get_buffer()
            k = min(len(room), end - pos)
            room[:k] = view[pos:pos + k]
            pos += k
            yield from self.buffer_updated(k)

    def get_buffer(self) -> memoryview:
        """The buffer the next bytes of the stream go into (at least 1 byte)."""
        if self._big is not None:
            return self._big[self._have:]
        return memoryview(self._buf)[self._end:]

    def buffer_updated(self, nbytes: int) -> Iterator[dict | DataFrame]:
        """``nbytes`` bytes were written at the start of the last :meth:`get_buffer`; yield the frames
        they complete, in order."""
        if self._big is not None:
            self._have += nbytes
            if self._have == len(self._big):
                view, self._big = self._big, None
                yield decode_body(view[4], view[_HEAD.size:])
            return
        self._end += nbytes
        stop, error = _scan(self._buf, 0, self._end, self.max_frame)
        whole = bytes(memoryview(self._buf)[:stop]) if stop else b""   # the one copy of small frames
        rest = self._end - stop
        if stop and rest:
            self._buf[:rest] = self._buf[stop:self._end]       # the incomplete frame's start to the front
        self._end = rest
        if error is None and rest >= _HEAD.size:
            self._grow()
        yield from _decode_whole(memoryview(whole), 0, stop)
        if error is not None:
            raise error

    def _grow(self) -> None:
        """The incomplete frame at the front of ``_buf`` moves to a buffer of its own if it is larger."""
        size = 4 + _HEAD.unpack_from(self._buf)[0]
        if size > len(self._buf):
            self._big = self._buffer(size)[:size]
            self._big[:self._end] = memoryview(self._buf)[:self._end]
            self._have, self._end = self._end, 0

    def _buffer(self, size: int) -> memoryview:
        """A buffer of at least ``size`` bytes that nobody else holds: a spare whose frame every
        holder has let go of (CPython: its only references are the list's and this call's), else a
        fresh anonymous ``mmap`` (its pages filled only as bytes arrive: an announced size costs
        nothing until sent), kept as a spare when there is room."""
        for spare in self._spares:
            if len(spare) >= size and sys.getrefcount(spare) <= 3:     # the list, ``spare``, the call
                return memoryview(spare)
        fresh = mmap.mmap(-1, size)
        if size <= SPARE_MAX:
            if len(self._spares) >= SPARE_BUFFERS:
                self._spares.remove(min(self._spares, key=len))
            self._spares.append(fresh)
        return memoryview(fresh)
