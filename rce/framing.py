"""The one framing for internal links (control plane, data plane, container bus).

A frame is ``u32 length | u8 kind | body`` (big-endian; ``length`` counts kind and
body). ``kind`` is :data:`CONTROL` (UTF-8 JSON object) or :data:`DATA`. A DATA
body is ``u8 op | u64 dst | u64 src | u64 call_id | payload`` where ``dst`` and
``src`` are interface (or bus handle) ids and ``payload`` is a ROS 1 serialized
message, carried as opaque bytes: no JSON and no re-encoding on internal hops.
"""
from __future__ import annotations

import asyncio
import json
import struct
from dataclasses import dataclass

from rce.errors import ProtocolError, RequestError

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
    """A decoded DATA frame. ``payload`` is a memoryview slice of the received buffer."""
    op: int
    dst: int
    src: int
    call_id: int
    payload: bytes | memoryview


def settle_call(pending: dict[int, "asyncio.Future"], f: DataFrame) -> None:
    """Complete the call future ``pending[f.call_id]`` from a SRV_RESP (result: the response
    bytes) or SRV_ERR frame (exception: :class:`RequestError` with the remote reason)."""
    fut = pending.get(f.call_id)
    if fut is None or fut.done():
        return
    if f.op == SRV_RESP:
        fut.set_result(bytes(f.payload))
    else:
        fut.set_exception(RequestError(bytes(f.payload).decode(errors="replace")))


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


def decode_body(kind: int, body: bytes) -> dict | DataFrame:
    """Decode a frame body by ``kind``; raises :class:`ProtocolError` on malformed input."""
    if kind == CONTROL:
        try:
            obj = json.loads(body)
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
    """Sans-I/O incremental decoder: ``feed(bytes)`` returns the complete frames so far.

    Raises :class:`ProtocolError` when a frame announces more than ``max_frame`` bytes."""

    def __init__(self, max_frame: int = DEFAULT_MAX_FRAME):
        self.max_frame = max_frame
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[dict | DataFrame]:
        self._buf += data
        out = []
        while len(self._buf) >= _HEAD.size:
            n, kind = _HEAD.unpack_from(self._buf)
            _check_length(n, self.max_frame)
            if len(self._buf) < 4 + n:
                break
            body = bytes(self._buf[_HEAD.size:4 + n])
            del self._buf[:4 + n]
            out.append(decode_body(kind, body))
        return out


async def read_frame(reader: asyncio.StreamReader, max_frame: int = DEFAULT_MAX_FRAME) -> dict | DataFrame:
    """Read one frame from ``reader``. Raises :class:`asyncio.IncompleteReadError` at EOF and
    :class:`ProtocolError` for an oversized or malformed frame."""
    head = await reader.readexactly(_HEAD.size)
    n, kind = _HEAD.unpack(head)
    _check_length(n, max_frame)
    return decode_body(kind, await reader.readexactly(n - 1))
