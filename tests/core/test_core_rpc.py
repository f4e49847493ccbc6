"""rce.transport.rpc: the control-plane peer over an in-memory pair of streams (no sockets)."""
from __future__ import annotations

import asyncio
import logging

import pytest
from memlink import pipe

from rce.plumbing.errors import NotFound, ProtocolError, RCEError, Timeout, Unavailable
from rce.transport.framing import MSG, encode_control, encode_data
from rce.transport.rpc import RpcPeer

STEP = 5.0   # s, the longest any single wait may take


async def stuck(args: dict) -> None:
    """A handler that never answers."""
    await asyncio.Event().wait()


async def pair(handlers_a=None, handlers_b=None, **kw) -> tuple[RpcPeer, RpcPeer]:
    (ra, wa), (rb, wb) = pipe()
    return (RpcPeer(ra, wa, handlers_a, name="a", **kw).start(),
            RpcPeer(rb, wb, handlers_b, name="b", **kw).start())


async def test_call_and_reply_both_ways():
    async def add(a):
        return a["x"] + a["y"]

    async def hello(a):
        return {"hi": a["name"]}
    a, b = await pair({"hello": hello}, {"add": add})
    assert await a.call("add", x=1, y=2) == 3
    assert await b.call("hello", name="b") == {"hi": "b"}
    assert await a.request("add", {"x": 5, "y": 5}, timeout=STEP) == 10
    assert await a.call("ping") is None                 # every peer answers ping
    assert len(a.calls) == len(b.calls) == 0


async def test_refusal_crosses_with_its_code():
    async def find(a):
        raise NotFound(f"no {a['what']}")
    a, _ = await pair(None, {"find": find})
    with pytest.raises(NotFound) as ei:
        await a.call("find", what="robot")
    assert ei.value.message == "no robot" and ei.value.code == "not_found"


async def test_a_crashing_handler_answers_internal_error(caplog):
    async def broken(a):
        return 1 / 0
    a, _ = await pair(None, {"broken": broken})
    with caplog.at_level(logging.ERROR):
        with pytest.raises(RCEError) as ei:
            await a.call("broken")
    assert ei.value.message == "internal error: ZeroDivisionError: division by zero"
    assert any(r.exc_info and r.exc_info[0] is ZeroDivisionError for r in caplog.records)


async def test_unknown_op():
    a, _ = await pair()
    with pytest.raises(ProtocolError, match="unknown control op 'nope'"):
        await a.call("nope")


async def test_timeout_is_a_timeout_not_unavailable():
    a, _ = await pair(None, {"stuck": stuck})
    with pytest.raises(Timeout) as ei:
        await a.call("stuck", timeout=0.05)
    assert isinstance(ei.value, TimeoutError) and not isinstance(ei.value, Unavailable)
    assert "'stuck'" in ei.value.message and "0.05 s" in ei.value.message
    assert len(a.calls) == 0


async def test_close_fails_the_calls_in_flight_and_runs_on_close_once():
    closes = []
    a, b = await pair(None, {"stuck": stuck})
    a.on_close = closes.append
    call = asyncio.ensure_future(a.call("stuck"))
    await asyncio.wait_for(_until(lambda: b.responder.in_flight == 1), STEP)
    await b.close()                                     # the other end goes away
    with pytest.raises(Unavailable, match="control link to a closed"):
        await asyncio.wait_for(call, STEP)
    await asyncio.wait_for(a.closed.wait(), STEP)
    await a.close()
    assert closes == [a]
    with pytest.raises(Unavailable, match="closed"):
        await a.call("stuck")
    a.notify("ignored")                                 # notifications on a closed link are ignored


async def test_notifications_run_their_handler_and_refusals_are_logged(caplog):
    got = asyncio.Queue()

    async def status(a):
        got.put_nowait(a)

    async def bad(a):
        raise NotFound("unknown container")
    a, _ = await pair(None, {"status": status, "bad": bad})
    with caplog.at_level(logging.WARNING, logger="rce.transport.rpc"):
        a.notify("bad")
        a.notify("status", cid=3)
        assert await asyncio.wait_for(got.get(), STEP) == {"cid": 3}
        await asyncio.wait_for(_until(lambda: any("refused" in r.getMessage() for r in caplog.records)), STEP)


async def test_data_frames_go_to_on_data():
    got = asyncio.Queue()
    a, b = await pair()
    b.on_data = got.put_nowait
    a.send_raw(encode_data(MSG, 4, 5, 0, b"payload"))
    f = await asyncio.wait_for(got.get(), STEP)
    assert (f.dst, f.src, bytes(f.payload)) == (4, 5, b"payload")


async def test_a_reply_to_a_non_integer_id_is_a_bad_frame():
    a, b = await pair()
    b.link.send(encode_control({"re": [1], "ok": True}))
    await asyncio.wait_for(a.closed.wait(), STEP)
    assert a.link.close_reason.startswith("bad frame: reply to [1]")


async def test_a_peer_that_reads_no_control_frames_is_cut_off():
    a, _ = await pair(max_buffer=100)
    a.link.writer.transport.waiting = 200               # twice the bound already waits unread
    with pytest.raises(Unavailable, match="saturated"):
        await a.call("ping")
    assert a.closed.is_set() and "saturated" in a.link.close_reason


async def test_renaming_a_peer_renames_its_errors():
    a, _ = await pair(None, {"stuck": stuck})
    a.name = "container:host1"
    with pytest.raises(Timeout, match="container:host1 did not answer"):
        await a.call("stuck", timeout=0.01)


async def test_keepalive_closes_a_silent_link():
    (ra, wa), _ = pipe()                                # nobody reads or answers on the other end
    a = RpcPeer(ra, wa, name="silent").start()
    a.keepalive(interval=0.01, timeout=0.05)
    await asyncio.wait_for(a.closed.wait(), STEP)
    assert a.link.close_reason.startswith("silent for")


async def _until(cond) -> None:
    """Yield to the loop until ``cond()`` holds (a condition, not a delay)."""
    while not cond():
        await asyncio.sleep(0)
