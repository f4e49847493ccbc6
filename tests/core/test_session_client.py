"""ClientSession (the robot side of a session), frames in, events and frames out, no sockets:
what the shared vectors (tests/vectors/session.json) do not pin: the pending table's waiters
get results and errors, a closed session refuses work, ids and tokens."""
from __future__ import annotations

import asyncio
import json

import pytest

from rce.plumbing.errors import ProtocolError, RequestError, Timeout, Unavailable
from rce.protocol.events import CallFailed, ErrorReceived, MessageReceived, ResponseReceived
from rce.protocol.session import BARRIER_PREFIX, ClientSession

pytestmark = pytest.mark.asyncio


def dm(**data) -> str:
    return json.dumps({"type": "DM", "data": data})


async def test_waiters_get_the_response_the_er_and_the_close():
    s = ClientSession()
    ok = s.call("echo", "Test/StringEcho", {"data": "a"})
    refused = s.call("echo2", "Test/StringEcho", {"data": "b"})
    lost = s.call("echo3", "Test/StringEcho", {"data": "c"})
    waiters = [asyncio.ensure_future(s.pending.wait(k, 5)) for k in (ok, refused, lost)]
    s.receive_text(dm(iTag="echo", type="Test/StringEcho", msgID=ok, msg={"data": "A"}), 0)
    s.receive_text(json.dumps({"type": "ER", "data": f"service call {refused!r} on 'echo2' failed: nope"}), 0)
    s.close("code 1006")
    assert await waiters[0] == {"data": "A"}
    with pytest.raises(RequestError, match="failed: nope"):
        await waiters[1]
    with pytest.raises(Unavailable, match="connection to the cloud closed: code 1006"):
        await waiters[2]
    assert len(s.pending) == 0
    assert [type(e) for e in s.events_received()] == [ResponseReceived, CallFailed, CallFailed]


async def test_a_closed_session_refuses_calls_barriers_and_sends():
    s = ClientSession()
    s.close("code 1000")
    for start in (lambda: s.call("i", "t", {}), lambda: s.barrier(), lambda: s.send("CC", {"containerTag": "c"})):
        with pytest.raises(Unavailable, match="closed: code 1000"):
            start()
    assert s.data_to_send() == [] and len(s.pending) == 0


async def test_fresh_msg_ids_and_barrier_tokens():
    s = ClientSession()
    ids = {s.call("i", "t", {}) for _ in range(20)}
    assert len(ids) == 20 and all(len(i) == 32 and int(i, 16) >= 0 for i in ids)
    token = s.barrier()
    assert token.startswith(BARRIER_PREFIX)
    cx = json.loads(s.data_to_send()[-1])
    assert cx == {"type": "CX", "data": {"connect": [{"tagA": f"{token}/a", "tagB": f"{token}/b"}]}}


async def test_a_call_with_a_bytes_request_sends_its_part():
    s = ClientSession()
    msg_id = s.call("fwd", "Test/StringEcho", b"\x02\x00\x00\x00hi", ids=["e" * 32])
    text, part = s.data_to_send()
    assert json.loads(text)["data"] == {"iTag": "fwd", "type": "Test/StringEcho", "msgID": msg_id, "msg*": "e" * 32}
    assert part == b"e" * 32 + b"\x02\x00\x00\x00hi"


async def test_a_call_that_cannot_be_encoded_leaves_nothing_pending():
    s = ClientSession()
    with pytest.raises(ProtocolError, match="32-hex-char id"):
        s.call("fwd", "t", b"x", ids=["nope"])
    assert len(s.pending) == 0 and s.data_to_send() == []


async def test_the_waiter_times_out_with_timeout():
    s = ClientSession()
    key = s.call("slow", "t", {})
    with pytest.raises(Timeout, match="did not answer"):
        await s.pending.wait(key, 0.01)
    # a late response is then an ordinary message
    s.receive_text(dm(iTag="slow", type="t", msgID=key, msg={}), 0)
    assert [type(e) for e in s.events_received()] == [MessageReceived]


async def test_a_response_before_anyone_waits_is_kept_for_the_waiter():
    s = ClientSession()
    key = s.call("echo", "t", {})
    s.receive_text(dm(iTag="echo", type="t", msgID=key, msg={"ok": 1}), 0)
    s.receive_text(json.dumps({"type": "ER", "data": f"late ER naming {key}"}), 0)    # not the call's any more
    assert [type(e) for e in s.events_received()] == [ResponseReceived, ErrorReceived]
    assert await s.pending.wait(key, 1) == {"ok": 1}
