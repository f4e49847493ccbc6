"""The one framing for internal links (control plane, data plane, container bus).

A frame is ``u32 length | u8 kind | body`` (big-endian; ``length`` counts kind and
body). ``kind`` is :data:`CONTROL` (UTF-8 JSON object) or :data:`DATA`. A DATA
body is ``u8 op | u64 dst | u64 src | u64 call_id | payload`` where ``dst`` and
``src`` are interface (or bus handle) ids and ``payload`` is a ROS 1 serialized
message, carried as opaque bytes: no JSON and no re-encoding on internal hops.
"""
from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass

from rce.errors import ProtocolError

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


def _check_length(n: int, max_frame: int) -> None:
    if n < 1:
        raise ProtocolError("frame length 0 leaves no room for its kind byte")
    if n - 1 > max_frame:
        raise ProtocolError(f"frame of {n - 1} bytes exceeds the limit of {max_frame} bytes")


class FrameDecoder:
    """Sans-I/O incremental decoder: bytes in (as they arrive from a stream), frames out.

    :meth:`frames` yields each complete frame as soon as it is decoded (a frame before a bad
    one is still delivered); :meth:`feed` returns them as a list. Whole frames in a chunk are
    decoded in place (a DATA payload is a view of the chunk); an incomplete frame's pieces
    are kept and joined once, when the last one arrives, so a large frame costs one copy.

    Raises :class:`ProtocolError` for a frame that announces more than ``max_frame`` bytes
    (as soon as its header is in) or is malformed; the stream is then out of step and the
    decoder must not be fed again."""

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME):
        self.max_frame = max_frame
        self._parts: list[bytes | memoryview] = []   # the start of an incomplete frame, as it came in
        self._have = 0                    # bytes in _parts
        self._need = _HEAD.size           # bytes the incomplete frame needs before decoding can go on

    def feed(self, data: bytes) -> list[dict | DataFrame]:
        """Every frame completed by ``data``, in order."""
        return list(self.frames(data))

    def frames(self, data: bytes) -> Iterator[dict | DataFrame]:
        """Yield every frame completed by ``data`` (immutable bytes), in order."""
        view = memoryview(data)
        pos, end = 0, len(data)
        while self._parts:                   # first complete the frame that began in earlier data
            missing = self._need - self._have
            if end - pos < missing:
                if pos < end:
                    self._parts.append(view[pos:])
                    self._have += end - pos
                return
            self._parts.append(view[pos:pos + missing])
            pos += missing
            buf = b"".join(self._parts)      # the frame's one copy: its pieces, no byte more
            self._parts.clear()
            n, kind = _HEAD.unpack_from(buf)
            _check_length(n, self.max_frame)
            if len(buf) < 4 + n:             # so far only its header
                self._parts.append(buf)
                self._have, self._need = len(buf), 4 + n
                continue
            yield decode_body(kind, memoryview(buf)[_HEAD.size:])
        while True:                          # whole frames, decoded in place
            if end - pos < _HEAD.size:
                need = _HEAD.size
                break
            n, kind = _HEAD.unpack_from(data, pos)
            _check_length(n, self.max_frame)
            if end - pos < 4 + n:
                need = 4 + n
                break
            start, pos = pos + _HEAD.size, pos + 4 + n
            yield decode_body(kind, view[start:pos])
        if pos < end:
            self._parts.append(view[pos:])
            self._have, self._need = end - pos, need
