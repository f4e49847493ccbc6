"""Sans I/O: the bounds a robot session keeps under hostile input (the JSON depth
limit, ER truncation, the ER token bucket and outbox bound, binary parts capped per session and per
endpoint with expiry in O(expired)) and the master's per-user quotas. The engine tests of the same
attacks are in tests/security/test_hostile_input.py."""
from __future__ import annotations

import json
import time

import pytest

from rce.plumbing.errors import ProtocolError
from rce.protocol.frames import Assembler, parse_frame
from rce.protocol.limits import (ER_BURST, MAX_ER_TEXT, MAX_JSON_DEPTH, PartBudget, TokenBucket, json_too_deep,
                                 short_repr, truncate)
from rce.protocol.events import RequestReady
from rce.protocol.schema import InterfaceComponent, NodeComponent
from rce.protocol.session import RobotSession, SessionLimits
from rce_master.state.master_state import MasterState, QuotaExceeded, Quotas


def ers(s: RobotSession) -> list[str]:
    return [json.loads(f)["data"] for f in s.data_to_send() if isinstance(f, str) and json.loads(f)["type"] == "ER"]


def part(i: int, payload: bytes = b"p") -> bytes:
    return f"{i:032x}".encode() + payload


# -- JSON depth ------------------------------------------------------------------------------------
def test_depth_scan_skips_strings_and_escapes():
    assert not json_too_deep(json.dumps({"s": "[" * 1000, "t": "\\\"[[[[" * 100}))
    assert json_too_deep("[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1))
    assert not json_too_deep("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH)
    wide = json.dumps([[i] for i in range(10_000)])            # many brackets, depth 2
    assert not json_too_deep(wide)


def test_a_frame_nested_1000_deep_is_an_er_and_the_session_goes_on():
    s = RobotSession("r1")
    s.receive_text('{"type": "DM", "data": ' + "[" * 1000 + "]" * 1000 + "}", 0)
    s.receive_text("{" * 100_000, 0)                           # unbalanced too: no RecursionError either
    assert ers(s) == [f"JSON nested deeper than the limit of {MAX_JSON_DEPTH} levels; dropped"] * 2
    s.receive_text('{"type": "CC", "data": {"containerTag": "c"}}', 0)
    assert [type(e) for e in s.events_received()] == [RequestReady]


def test_parse_frame_finds_refs_only_where_a_star_key_can_be():
    ref = "ab" * 16
    assert parse_frame(json.dumps({"type": "DM", "data": {"msg*": ref}})) == (
        {"type": "DM", "data": {"msg*": ref}}, [ref])
    assert parse_frame('{"type": "DM", "data": {"msg": "a*"}}')[1] == []
    with pytest.raises(ProtocolError, match="32-hex-char id, got 'x'"):
        parse_frame('{"msg*": "x"}')


# -- ERs ------------------------------------------------------------------------------------------
def test_er_text_is_cut_at_the_limit_with_a_marker():
    assert truncate("a" * MAX_ER_TEXT) == "a" * MAX_ER_TEXT
    cut = truncate("é" * MAX_ER_TEXT)                          # 2 bytes each: never split inside one
    assert cut.startswith("é" * (MAX_ER_TEXT // 2)) and cut.endswith(f"[{MAX_ER_TEXT} more bytes]")
    assert len(short_repr("v" * 1_000_000)) < 100 and len(short_repr([[["x" * 10**6] * 10**3]])) < 200


def test_bad_frames_with_big_values_cost_bounded_ers():
    # the probe: 150 bad frames with big values (1 MiB there; 100 KiB here, for time) to a robot that does not read
    s = RobotSession("r1")
    big = "v" * (100 * 1024)
    frames = [json.dumps({"type": "CC", "data": {"containerTag": [big]}}), json.dumps({"type": big})]
    for i in range(150):
        s.receive_text(frames[i % 2], 0)
    st = s.stats()
    assert st["errors"] == ER_BURST and st["errors_dropped"] == 150 - ER_BURST
    texts = ers(s)
    assert len(texts) == ER_BURST and max(len(t.encode()) for t in texts) <= MAX_ER_TEXT + 40


def test_er_bucket_refills_at_its_rate():
    b = TokenBucket(rate=10, burst=2)
    assert [b.take(0.0) for _ in range(3)] == [True, True, False]
    assert not b.take(0.05) and b.take(0.1) and not b.take(0.1)
    assert [b.take(100.0) for _ in range(3)] == [True, True, False]     # never more than the burst


def test_answers_to_requests_are_not_rate_limited():
    s = RobotSession("r1", SessionLimits(er_rate=0.001, er_burst=1, queue_size=100))
    for i in range(5):
        s.receive_text(json.dumps({"type": "CX", "data": {"connect": [{"tagA": f"t{i}/a", "tagB": f"t{i}/b"}]}}), 0)
        s.events_received()
        s.request_done(f"interface 't{i}/a' does not exist")
    assert len(ers(s)) == 5 and s.stats()["errors_dropped"] == 0


# -- binary parts ----------------------------------------------------------------------------------
def test_pending_parts_are_capped_in_number_per_session():
    a = Assembler(max_pending_parts=3)
    for i in range(3):
        a.feed_binary(part(i), 0)
    with pytest.raises(ProtocolError, match="3 binary parts already wait"):
        a.feed_binary(part(9), 0)
    a.feed_binary(part(1, b"again"), 0)                        # the same id replaces its part
    assert a.pending == 3 and a.pending_bytes == 2 + 5


def test_the_endpoint_budget_is_shared_and_given_back():
    budget = PartBudget(max_bytes=10)
    a, b = RobotSession("a", budget=budget), RobotSession("b", budget=budget)
    a.receive_binary(part(1, b"x" * 6), 0)
    b.receive_binary(part(2, b"y" * 6), 0)
    assert "on this endpoint exceed 10 bytes" in ers(b)[0] and budget.held == 6 and budget.refused == 1
    a.end()                                                    # a's session ended: its bytes go back
    b.receive_binary(part(2, b"y" * 6), 0)
    assert ers(b) == [] and budget.held == 6
    b.receive_text(json.dumps({"type": "DM", "data": {"iTag": "i", "type": "t", "msg*": f"{2:032x}"}}), 0)
    assert budget.held == 0                                    # consumed by its message
    b.receive_binary(part(3, b"z"), 0)
    b.tick(1000)
    assert budget.held == 0 and b.assembler.pending == 0


def test_expiry_costs_o_expired():
    a = Assembler(expiry=60, max_pending_parts=20_000, max_pending_messages=20_000)
    for i in range(20_000):
        a.feed_binary(part(i), float(i) / 1000)                # parts arrive over 20 s
    for i in range(5_000):
        a.feed_text(json.dumps({"type": "DM", "data": {"iTag": "x", "msg*": f"{i + 10**6:032x}"}}), 20.0)
    t = time.perf_counter()
    for k in range(1000):                                      # ticks that expire nothing
        assert a.expire(59.0 + k * 0.0001) == []
    assert time.perf_counter() - t < 0.05
    reasons = a.expire(70.0)                                   # the parts of the first 10 s
    assert len(reasons) == 10_000 and a.pending == 10_000 + 5_000
    assert len(a.expire(100.0)) == 10_000 + 5_000 and a.pending == 0 and a.pending_bytes == 0


def test_a_part_waiting_for_its_message_expires_with_it():
    a = Assembler(expiry=5)
    a.feed_binary(part(1), 0)
    assert a.feed_text(json.dumps({"m*": [f"{1:032x}", f"{2:032x}"]}), 4) == []
    assert a.expire(5.5) == []                                 # part 1 waits for the message's other part
    reasons = a.expire(9.5)
    assert len(reasons) == 2 and "message" in reasons[0] and f"{1:032x}" in reasons[1] and a.pending == 0


def test_a_reused_id_is_consumed_once_per_message():
    a = Assembler()
    ref = f"{7:032x}"
    assert a.feed_text(json.dumps({"n": 1, "m*": ref}), 0) == []
    assert a.feed_text(json.dumps({"n": 2, "m*": ref}), 0) == []
    assert a.feed_binary(part(7, b"A"), 0) == [{"n": 1, "m": b"A"}]
    assert a.feed_binary(part(7, b"B"), 0) == [{"n": 2, "m": b"B"}] and a.pending == 0


# -- quotas (the master) ---------------------------------------------------------------------------
def test_per_user_quotas_refuse_with_a_clear_error_and_leave_other_users_alone():
    ms = MasterState(quotas=Quotas(containers=2, nodes=1, interfaces=1))
    ms.register_taskset("robot", "re1", "hostA", {"data_addr": "tcp://10.0.0.1:10030", "ws_url": "ws://hostA:9010/"})
    ms.register_taskset("container", "ch1", "hostB", {"sandbox": "process-group"})
    for ctag in ("c1", "c2"):
        ms.add_container("alice", "r1", ctag, None)
    with pytest.raises(QuotaExceeded, match=r"user 'alice' already has 2 containers.*--max-containers"):
        ms.add_container("alice", "r1", "c3", None)
    ms.add_container("bob", "r2", "c1", None)                  # another user's quota is its own
    node = {"nodeTag": "n1", "pkg": "Test", "exe": "e"}
    ms.add_node("alice", NodeComponent.model_validate({**node, "containerTag": "c1"}))
    with pytest.raises(QuotaExceeded, match="1 nodes"):
        ms.add_node("alice", NodeComponent.model_validate({**node, "containerTag": "c2", "nodeTag": "n2"}))
    spec = {"endpointTag": "c1", "interfaceType": "PublisherInterface", "className": "std_msgs/String"}
    ms.add_interface("alice", "r1", InterfaceComponent.model_validate({**spec, "interfaceTag": "i1"}))
    with pytest.raises(QuotaExceeded, match="1 interfaces"):
        ms.add_interface("alice", "r1", InterfaceComponent.model_validate({**spec, "interfaceTag": "i2"}))
    ms.remove_container("alice", "c2")                         # freed: room again
    ms.add_container("alice", "r1", "c4", None)
    assert Quotas(containers=0).check("alice", "containers", [("alice", i) for i in range(10**4)]) is None
