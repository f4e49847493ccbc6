"""rce.transport.link: the framed link, serve-and-reply and settle, on in-memory streams (no sockets)."""
from __future__ import annotations

import asyncio
import logging
import struct

import pytest
from memlink import lone, pipe

from rce.transport import framing
from rce.plumbing.errors import NotFound, RequestError, Unavailable
from rce.transport.framing import CONTROL, MSG, SRV_ERR, SRV_RESP, DataFrame, encode_control, encode_data
from rce.transport.link import JOIN_MAX, FramedLink, LinkFull, Responder, settle_reply
from rce.plumbing.pending import PendingCalls

STEP = 5.0   # s, the longest any single wait may take


def link_on(reader, writer, **kw) -> tuple[FramedLink, list, list]:
    frames, closes = [], []
    link = FramedLink(reader, writer, name="test", on_frame=kw.pop("on_frame", frames.append),
                      on_close=closes.append, **kw)
    return link, frames, closes


async def closed(link: FramedLink) -> None:
    await asyncio.wait_for(link.closed.wait(), STEP)
    await asyncio.wait_for(link.wait_closed(), STEP)


# -- reading ------------------------------------------------------------------------------------------
async def test_frames_in_order_then_eof_closes_once():
    link, frames, closes = link_on(*lone(encode_control({"a": 1}) + encode_data(MSG, 2, 3, 0, b"xy"), eof=True))
    link.start()
    await closed(link)
    assert frames[0] == {"a": 1} and bytes(frames[1].payload) == b"xy"
    assert closes == [link] and link.close_reason == "closed by the peer"
    assert link.writer.transport.closing
    link.close()                                   # idempotent: on_close ran once
    assert closes == [link]


async def test_bad_frame_is_logged_and_closes_after_the_good_ones(caplog):
    bad = struct.pack("!IB", 1, 9)
    link, frames, closes = link_on(*lone(encode_control({"first": True}) + bad + encode_control({"never": 1})))
    with caplog.at_level(logging.WARNING, logger="rce.transport.link"):
        link.start()
        await closed(link)
    assert frames == [{"first": True}]
    assert closes == [link] and "unknown frame kind 9" in link.close_reason
    assert any("bad frame" in r.getMessage() for r in caplog.records)


async def test_oversized_frame_closes_from_its_header():
    link, frames, closes = link_on(*lone(struct.pack("!IB", 1001, CONTROL)), max_frame=999)
    link.start()
    await closed(link)
    assert frames == [] and "1000 bytes" in link.close_reason


async def test_a_failing_handler_is_logged_with_its_traceback_and_closes(caplog):
    def boom(frame):
        raise ZeroDivisionError("handler bug")
    link, _, closes = link_on(*lone(encode_control({})), on_frame=boom)
    with caplog.at_level(logging.ERROR, logger="rce.transport.link"):
        link.start()
        await closed(link)
    assert closes == [link] and "ZeroDivisionError" in link.close_reason
    assert any(r.exc_info and r.exc_info[0] is ZeroDivisionError for r in caplog.records)


async def test_protocol_error_from_the_handler_is_a_bad_frame():
    def refuse(frame):
        raise framing.ProtocolError("reply to a request that does not exist")
    link, _, _ = link_on(*lone(encode_control({})), on_frame=refuse)
    link.start()
    await closed(link)
    assert link.close_reason == "bad frame: reply to a request that does not exist"


async def test_close_from_the_handler_stops_delivery():
    got = []

    def first_only(frame):
        got.append(frame)
        link.close("enough")
    link, _, closes = link_on(*lone(encode_control({"n": 1}) + encode_control({"n": 2})), on_frame=first_only)
    link.start()
    await closed(link)
    assert got == [{"n": 1}] and closes == [link] and link.close_reason == "enough"


async def test_close_is_idempotent_and_ends_the_read_loop():
    link, _, closes = link_on(*lone())
    link.start()
    link.close("first")
    link.close("second")
    await closed(link)
    assert closes == [link] and link.close_reason == "first"


async def test_last_rx_moves_with_received_bytes():
    reader, writer = lone()
    link, frames, _ = link_on(reader, writer)
    link.start()
    before = link.last_rx
    reader.feed_data(encode_control({"k": 1}))
    reader.feed_eof()
    await closed(link)
    assert frames == [{"k": 1}] and link.last_rx >= before


# -- writing ------------------------------------------------------------------------------------------
async def pass_ends() -> None:
    """The loop pass in which the test wrote has ended: a callback scheduled now runs after the link's."""
    done = asyncio.get_running_loop().create_future()
    asyncio.get_running_loop().call_soon(done.set_result, None)
    await done


async def test_offer_writes_header_and_payload_within_the_bound():
    link, _, _ = link_on(*lone(), max_buffer=100)
    assert link.offer(b"head", memoryview(b"payload"))
    await pass_ends()
    assert bytes(link.writer.transport.written) == b"headpayload"


async def test_offer_drops_and_counts_past_the_bound():
    link, _, _ = link_on(*lone(), max_buffer=100)
    t = link.writer.transport
    t.waiting = 90
    assert not link.offer(b"h" * 5, b"p" * 10)        # 90 + 15 > 100
    assert link.offer(b"h" * 5, b"p" * 5)             # 90 + 10 = 100
    await pass_ends()
    assert link.dropped == 1 and len(t.written) == 10


async def test_an_idle_link_takes_a_frame_larger_than_its_bound():
    link, _, _ = link_on(*lone(), max_buffer=10)
    assert link.offer(b"h", b"p" * 50) and link.dropped == 0


async def test_send_may_pass_the_offer_bound_up_to_the_hard_bound():
    link, _, _ = link_on(*lone(), max_buffer=100)
    t = link.writer.transport
    t.waiting = 150
    assert not link.offer(b"x")
    link.send(b"c" * 50)                               # 200 = 2 x max_buffer: still goes
    t.waiting = 145                                    # + the 50 corked
    with pytest.raises(LinkFull) as ei:
        link.send(b"c" * 6)
    assert isinstance(ei.value, Unavailable) and "saturated" in ei.value.message
    await pass_ends()
    assert (link.dropped, link.refused) == (1, 1) and bytes(t.written) == b"c" * 50


async def test_a_pass_s_frames_go_together_in_one_write_when_the_pass_ends():
    link, _, _ = link_on(*lone(), max_buffer=100)
    t = link.writer.transport
    assert link.offer(b"m1", b"+p")
    assert link.offer(b"m2")
    link.send(b"c3")
    assert link.offer(b"m4", b"+q")
    assert bytes(t.written) == b"" and link.waiting == 12        # corked: they count towards the bounds
    await pass_ends()                                            # no timer: the pass's own end
    assert bytes(t.written) == b"m1+pm2c3m4+q" and t.writes == 1  # one write for the pass
    assert link.offer(b"m5")                                     # a lone message: its own pass, its own write
    await pass_ends()
    assert bytes(t.written).endswith(b"m5") and t.writes == 2


async def test_a_large_payload_goes_after_what_the_cork_holds_uncopied():
    link, _, _ = link_on(*lone(), max_buffer=1 << 20)
    t = link.writer.transport
    big = memoryview(b"b" * (JOIN_MAX + 1))
    assert link.offer(b"m1") and link.offer(b"h2", big)
    assert bytes(t.written) == b"m1h2" + bytes(big)              # in order, at once: the cork first


async def test_corked_frames_count_towards_the_bound_and_go_before_a_close():
    link, _, _ = link_on(*lone(), max_buffer=100)
    t = link.writer.transport
    assert link.offer(b"x")
    assert link.offer(b"h" * 50, b"p" * 40)          # corked: 90 bytes wait
    assert not link.offer(b"h" * 5, b"p" * 10)        # 90 + 15 > 100
    assert link.dropped == 1
    link.close()
    assert bytes(t.written) == b"x" + b"h" * 50 + b"p" * 40


async def test_writes_on_a_closed_link():
    link, _, _ = link_on(*lone())
    link.close()
    assert not link.offer(b"x") and link.dropped == 1
    with pytest.raises(Unavailable, match="closed"):
        link.send(b"x")


# -- under pressure: the link's queue (module doc) ----------------------------------------------------
HIGH = 64 * 1024          # the in-memory transport's high-water mark (rce.transport.link.HIGH_WATER)


def pressed(**kw) -> tuple[FramedLink, list]:
    """A started link whose transport is past its high-water mark (the peer is not reading);
    ``drops`` records the tags ``on_drop`` hears of."""
    drops = []
    link, _, _ = link_on(*lone(), on_drop=drops.append, **kw)
    link.start()
    link.writer.transport.waiting = HIGH + 1
    return link, drops


async def drained(link: FramedLink) -> None:
    """The peer read everything: the transport's buffer is empty and it says so."""
    await asyncio.sleep(0)                           # start() takes the transport over on the next pass
    link.writer.transport.waiting = 0
    link.writer.transport.protocol.resume_writing()


async def test_under_pressure_frames_wait_in_order_and_go_out_when_the_peer_reads():
    link, drops = pressed()
    assert link.offer(b"m1") and link.offer(b"m2", b"+p")
    link.send(b"c3")                                 # a frame that must not be lost keeps its place
    assert link.offer(b"m4")
    assert link.held == 4 and bytes(link.writer.transport.written) == b""
    await drained(link)
    assert bytes(link.writer.transport.written) == b"m1m2+pc3m4"
    assert link.held == 0 and link.dropped == 0 and drops == []
    assert link.offer(b"m5") and link.held == 0                  # straight through again: corked, not queued
    await pass_ends()
    assert bytes(link.writer.transport.written).endswith(b"m5")


async def test_offered_frames_past_max_delay_are_dropped_oldest_first_and_counted(monkeypatch):
    loop = asyncio.get_running_loop()
    now = [1000.0]
    monkeypatch.setattr(loop, "time", lambda: now[0])
    link, drops = pressed(max_delay=0.5)
    link.offer(b"old1", b"", "t1")
    link.send(b"ctl")
    link.offer(b"old2", b"", "t2")
    now[0] += 0.4
    link.offer(b"new1", b"", "t3")
    now[0] += 0.2                                    # old1, old2: 0.6 s; new1: 0.2 s
    link.offer(b"new2", b"", "t4")                   # the head of the queue (old1) expires here
    assert drops == ["t1"] and link.expired == 1
    await drained(link)
    assert bytes(link.writer.transport.written) == b"ctlnew1new2"     # the control frame is never dropped
    assert drops == ["t1", "t2"] and (link.dropped, link.expired) == (2, 2)


async def test_a_full_queue_drops_its_oldest_offered_frame_for_a_newer_one():
    link, drops = pressed(max_buffer=HIGH + 1 + 10)      # room for 10 bytes beyond the transport's
    assert link.offer(b"aaaa", b"", "a") and link.offer(b"bbbb", b"", "b")
    link.send(b"cc")                                     # 10 bytes queued
    assert link.offer(b"dddd", b"", "d")                 # "a" makes room
    assert drops == ["a"] and link.dropped == 1 and link.expired == 0
    assert not link.offer(b"e" * 11, b"", "e")           # larger than the room: refused, nothing else lost
    assert drops == ["a"] and link.dropped == 2
    await drained(link)
    assert bytes(link.writer.transport.written) == b"bbbbccdddd"


async def test_a_frame_that_must_not_be_lost_takes_the_room_of_offered_ones():
    link, drops = pressed(max_buffer=HIGH + 1 + 8, hard_buffer=HIGH + 1 + 8)
    link.offer(b"aaaa", b"", "a")
    link.offer(b"bbbb", b"", "b")
    link.send(b"cccccc")                                 # 6 bytes: "a" and "b" both make way
    assert drops == ["a", "b"]
    with pytest.raises(LinkFull):
        link.send(b"x" * 3)                              # only must-not-lose frames left: refused
    assert link.refused == 1
    await drained(link)
    assert bytes(link.writer.transport.written) == b"cccccc"


async def test_what_waits_is_dropped_and_counted_when_the_link_closes():
    link, drops = pressed()
    link.offer(b"m1", b"", 1)
    link.send(b"c2")
    link.close()
    assert drops == [1] and link.held == 0 and link.dropped == 1


# -- serve and reply ----------------------------------------------------------------------------------
async def serve(responder: Responder, handler) -> tuple[str, object]:
    done = asyncio.get_running_loop().create_future()
    responder.serve(handler, lambda r: done.set_result(("reply", r)), lambda e: done.set_result(("refuse", e)),
                    "test request")
    return await asyncio.wait_for(done, STEP)


async def test_responder_replies_with_the_result():
    async def handler():
        return {"ok": 1}
    assert await serve(Responder("t"), handler) == ("reply", {"ok": 1})


async def test_responder_refuses_with_the_rce_error_as_raised():
    async def handler():
        raise NotFound("no such thing")
    how, e = await serve(Responder("t"), handler)
    assert how == "refuse" and type(e) is NotFound and e.message == "no such thing"


async def test_responder_turns_a_crash_into_an_internal_error_and_logs_it(caplog):
    async def handler():
        raise KeyError("k")
    with caplog.at_level(logging.ERROR, logger="rce.transport.link"):
        how, e = await serve(Responder("t"), handler)
    assert how == "refuse" and e.message == "internal error: KeyError: 'k'"
    assert any(r.exc_info and r.exc_info[0] is KeyError for r in caplog.records)


async def test_responder_bounds_the_requests_in_flight():
    gate = asyncio.Event()
    r = Responder("t", max_in_flight=1)

    async def slow():
        await gate.wait()
        return "late"
    first = asyncio.get_running_loop().create_future()
    r.serve(slow, first.set_result, first.set_exception, "first")
    how, e = await serve(r, slow)
    assert how == "refuse" and isinstance(e, Unavailable) and r.refused == 1
    gate.set()
    assert await asyncio.wait_for(first, STEP) == "late"
    await r.tasks.cancel_all()
    assert r.in_flight == 0


async def test_settle_reply():
    calls = PendingCalls("peer")
    ok, bad = calls.open(), calls.open()
    assert settle_reply(calls, DataFrame(SRV_RESP, 0, 0, ok, memoryview(b"resp")))
    assert settle_reply(calls, DataFrame(SRV_ERR, 0, 0, bad, memoryview(b"it broke")))
    assert not settle_reply(calls, DataFrame(SRV_RESP, 0, 0, 999, memoryview(b"late")))
    assert await calls.wait(ok, STEP) == b"resp"
    with pytest.raises(RequestError, match="it broke"):
        await calls.wait(bad, STEP)


async def test_a_pair_of_links_talks_both_ways():
    (ra, wa), (rb, wb) = pipe()
    got_a, got_b = asyncio.Queue(), asyncio.Queue()
    a = FramedLink(ra, wa, name="a", on_frame=got_a.put_nowait).start()
    b = FramedLink(rb, wb, name="b", on_frame=got_b.put_nowait).start()
    a.send(encode_control({"to": "b"}))
    b.offer(framing.encode_data_header(MSG, 1, 2, 0, 3), b"abc")
    assert await asyncio.wait_for(got_b.get(), STEP) == {"to": "b"}
    assert bytes((await asyncio.wait_for(got_a.get(), STEP)).payload) == b"abc"
    a.close()
    await closed(b)                                   # EOF reaches the other end
    assert b.close_reason == "closed by the peer"


async def test_bytes_before_start_come_first_then_a_large_frame_arrives_whole_without_a_copy():
    """What the stream reader took before start() is decoded first; the link then receives through
    its buffered protocol: a frame larger than the decoder's chunk, split over many reads, arrives
    whole, its payload a view of the buffer it was received into (handed on: no copy)."""
    (ra, wa), (rb, wb) = pipe()
    got = asyncio.Queue()
    b = FramedLink(rb, wb, name="b", on_frame=got.put_nowait)
    wa.transport.write(encode_control({"early": 1}))          # before b starts: into b's stream reader
    b.start()
    assert await asyncio.wait_for(got.get(), STEP) == {"early": 1}
    big = bytes(range(256)) * 8192                                # 2 MiB, 32 reads of 64 KiB
    wa.transport.write(framing.encode_data_header(MSG, 1, 2, 3, len(big)) + big + encode_control({"after": 1}))
    f = await asyncio.wait_for(got.get(), STEP)
    assert bytes(f.payload) == big and (f.dst, f.src, f.call_id) == (1, 2, 3)
    assert isinstance(f.payload, memoryview) and not isinstance(f.payload.obj, bytes)   # the receive buffer itself
    assert await asyncio.wait_for(got.get(), STEP) == {"after": 1}
    b.close()
