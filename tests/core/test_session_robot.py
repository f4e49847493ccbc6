"""RobotSession (the cloud side of a robot's session), frames in, events and frames out, no
sockets: what the shared vectors (tests/vectors/session.json) do not pin, and the check that
every bad input of tests/engine/test_bad_input.py is covered at the session level."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest

from rce.interfaces.kind import InterfaceType, Kind, Side
from rce.plumbing.errors import ProtocolError, RequestError
from rce.protocol.frames import ID_LEN, Assembler
from rce.protocol.limits import PartBudget
from rce.protocol.events import CaughtUp, CloseLink, Deliver, Lagging, ServiceCall
from rce.protocol.robot_outbox import CONTROL_BACKLOG
from rce.protocol.session import ResumeOptions, RobotSession, SessionLimits, robot_interface_type

TESTS = Path(__file__).resolve().parents[1]
VECTORS = {v["name"]: v for v in json.loads((TESTS / "vectors" / "session.json").read_text())["robot"]}

# Each test of tests/engine/test_bad_input.py -> the robot vectors that check the same input at the
# session level, or why the session has no part in it.
BAD_INPUT = {
    "test_malformed_json": ["bad_malformed_json"],
    "test_unknown_message_type": ["bad_unknown_type"],
    "test_missing_keys": ["bad_missing_keys", "bad_values"],
    "test_unknown_tags": ["bad_unknown_tags"],
    "test_unknown_package_names_pkg_and_exe": ["bad_unknown_tags"],          # the master refuses: request_done
    "test_unpairable_interfaces": ["bad_interface_type", "bad_unknown_tags"],
    "test_unknown_message_class": ["bad_unknown_tags"],                       # the master refuses: request_done
    "test_message_that_does_not_fit_its_class": ["bad_message_for_its_interface"],
    "test_frame_over_size_limit": ["bad_frame_over_size_limit"],
    "test_binary_part_errors": ["bad_binary_parts"],
    "test_bad_credentials_at_login": "the master's HTTP login: no session yet",
    "test_bad_credentials_at_websocket": "the websocket handshake: no session yet",
    "test_a_2013_client_that_only_reads_frames_learns_its_login_failed": "the websocket handshake: no session yet",
    "test_duplicate_robot_id_refused": "the websocket handshake: no session yet",
    "test_a_bad_admin_op_is_refused_by_the_master_naming_the_key": "the master's admin API: no robot session",
}


def test_every_bad_input_has_its_session_vectors():
    tree = ast.parse((TESTS / "engine" / "test_bad_input.py").read_text())
    tests = {f.name for f in tree.body if isinstance(f, ast.AsyncFunctionDef | ast.FunctionDef)
             and f.name.startswith("test_")}
    assert tests == set(BAD_INPUT), "map each test of test_bad_input.py to its session vectors"
    for name, covered in BAD_INPUT.items():
        if isinstance(covered, list):
            assert covered and all(v in VECTORS for v in covered), name


def frames_of(s: RobotSession) -> list:
    return [json.loads(f) if isinstance(f, str) else f for f in s.data_to_send()]


def ers(s: RobotSession) -> list[str]:
    return [f["data"] for f in frames_of(s) if isinstance(f, dict) and f["type"] == "ER"]


def test_dm_to_the_robot_with_bytes_goes_as_its_binary_part():
    s = RobotSession("r1")
    s.send_dm("cam", "sensor_msgs/Image", "", b"\x00\x01raw", data=True)
    text, part = s.data_to_send()
    msg = json.loads(text)
    ref = msg["data"]["msg*"]
    assert part[:ID_LEN].decode() == ref and part[ID_LEN:] == b"\x00\x01raw"
    a = Assembler()                               # what the robot makes of it
    assert a.feed_text(text, 0) == [] and a.feed_binary(part, 0)[0]["data"]["msg"] == b"\x00\x01raw"


def test_data_to_send_one_message_at_a_time_keeps_parts_with_their_message():
    s = RobotSession("r1")
    s.send_dm("a", "t", "", b"1", data=True)
    s.send_status({"topic": "iu", "iTag": "a", "status": True})
    assert json.loads(s.data_to_send(1)[0])["type"] == "ST"         # control before the state lane's data
    assert s.outbox == 1 and s.out_data == 1
    second = s.data_to_send(1)
    assert len(second) == 2 and isinstance(second[0], str) and isinstance(second[1], bytes)
    assert s.data_to_send(1) == [] and s.stats()["msgs_out"] == 2


def test_a_robot_that_does_not_read_is_closed_once_and_loses_nothing():
    # STs are never dropped (ERs are: tests/core/test_session_limits.py)
    s = RobotSession("r1", SessionLimits(queue_size=2))
    for i in range(CONTROL_BACKLOG * 2 + 5):
        s.send_status({"topic": "node", "status": f"s{i}"})
    closes = [e for e in s.events_received() if isinstance(e, CloseLink)]
    assert len(closes) == 1 and "'r1' does not read" in closes[0].reason
    assert [f["data"]["status"] for f in frames_of(s)] == [f"s{i}" for i in range(CONTROL_BACKLOG * 2 + 5)]


def test_request_done_without_a_request_is_a_bug():
    with pytest.raises(ProtocolError, match="no request in flight"):
        RobotSession("r1").request_done()


def test_interface_types_of_the_robot_side():
    t = robot_interface_type("ServiceConverter")                      # RCE alpha name
    assert t is InterfaceType.SERVICE_CLIENT_CONVERTER and (t.kind, t.side) == (Kind.SERVICE_CLIENT, Side.CONVERTER)
    assert robot_interface_type("PublisherForwarder") is InterfaceType.PUBLISHER_FORWARDER
    with pytest.raises(RequestError, match="PublisherInterface is a container interface"):
        robot_interface_type("PublisherInterface")
    with pytest.raises(ProtocolError, match="unknown interface type 'Publisher'"):
        RobotSession("r1").add_interface("x", "Publisher", "std_msgs/String")


def test_removed_interface_takes_no_more_dms():
    s = RobotSession("r1")
    s.add_interface("req", "SubscriberConverter", "std_msgs/String")
    dm = {"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": "x"}}}
    s.receive_text(json.dumps(dm), 0)
    assert s.events_received() == [Deliver("req", dm["data"])]
    s.remove_interface("req")
    s.receive_text(json.dumps(dm), 0)
    assert s.events_received() == [] and ers(s) == ["DM: no interface 'req' on robot 'r1'"]


def test_an_endpoint_behind_the_robot_longer_than_max_lag_sheds_topic_messages_only():
    s = RobotSession("r1", SessionLimits(max_lag=1.0))
    s.add_interface("req", "SubscriberConverter", "std_msgs/String")
    s.add_interface("srv", "ServiceProviderConverter", "Test/StringEcho")

    def dm(itag: str, data: str, msg_id: str = "") -> str:
        cls = "Test/StringEcho" if itag == "srv" else "std_msgs/String"
        return json.dumps({"type": "DM", "data": {"iTag": itag, "type": cls, "msgID": msg_id, "msg": {"data": data}}})

    def take(frame: str, waiting: int, now: float) -> list[type]:
        s.backlog(waiting, now)
        s.receive_text(frame, now)
        return [type(e) for e in s.events_received()]
    assert take(dm("req", "a"), 5, 10.0) == [Deliver]          # behind since 10.0
    assert take(dm("req", "b"), 4, 10.9) == [Deliver]          # 0.9 s: a burst, not a lag
    assert take(dm("req", "c"), 3, 11.2) == [Lagging]          # 1.2 s behind: shed, said once
    assert take(dm("req", "d"), 2, 11.3) == []
    assert take(dm("srv", "e", "call-1"), 1, 11.4) == [ServiceCall]   # a service call is never shed
    assert take(dm("req", "f"), 3, 12.0) == [Deliver]          # still behind, but 1.1 s since "b": one goes
    assert take(dm("req", "g"), 2, 12.1) == []
    assert take(dm("req", "h"), 0, 12.2) == [CaughtUp, Deliver]    # caught up: the newest goes
    assert take(dm("req", "i"), 1, 20.0) == [Deliver]          # a new lag starts from its own beginning
    assert s.stats()["shed"] == 3 and s.stats()["dropped_in"] == 0
    assert frames_of(s) == [{"type": "ST", "data": {"topic": "lag", "status": "shedding", "behind_s": 1.2,
                                                    "max_lag_s": 1.0}},
                            {"type": "ST", "data": {"topic": "lag", "status": "caught_up", "shed": 3}}]  # no ER
    never = RobotSession("r2", SessionLimits(max_lag=None))
    never.add_interface("req", "SubscriberConverter", "std_msgs/String")
    for t in (10.0, 12.0, 12.1):
        never.backlog(5, t)
        never.receive_text(dm("req", "x"), t)
    assert [type(e) for e in never.events_received()] == [Deliver] * 3 and never.stats()["shed"] == 0


def test_a_dm_with_a_legacy_service_type_routes_as_service_client():
    s = RobotSession("r1")
    s.add_interface("prov", "ServiceConverter", "Test/StringEcho")
    dm = {"iTag": "prov", "type": "Test/StringEcho", "msgID": "c0", "msg": {"data": "reply"}}
    s.receive_text(json.dumps({"type": "DM", "data": dm}), 0)
    assert s.events_received() == [Deliver("prov", dm)]


def test_one_robots_bad_input_leaves_another_session_alone():
    a, b = RobotSession("a"), RobotSession("b")
    for s in (a, b):
        s.add_interface("req", "SubscriberConverter", "std_msgs/String")
    a.receive_text('{"type": "CN", "data": ', 0)
    a.receive_binary(b"x" * 5, 0)
    good = json.dumps({"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msg": {"data": "x"}}})
    b.receive_text(good, 0)
    assert len(ers(a)) == 2 and a.stats()["errors"] == 2
    assert frames_of(b) == [] and [type(e) for e in b.events_received()] == [Deliver]
    assert b.stats()["errors"] == 0


def test_stats_names_every_counter_the_endpoint_exports():
    from rce_robot.endpoint import SESSION_COUNTERS
    stats = RobotSession("r1").stats()
    assert set(SESSION_COUNTERS) <= set(stats)
    assert {"pending_binary", "outbox", "requests_waiting", "held", "calls", "interfaces"} <= set(stats)


def test_endpoint_metrics_sum_live_and_ended_sessions():
    from types import SimpleNamespace

    from prometheus_client import generate_latest

    from rce_robot.endpoint import Metrics
    live, ended = RobotSession("a"), RobotSession("b")
    live.receive_text("nope", 0)
    live.send_dm("x", "t", "", {}, data=True)
    ended.receive_text("[]", 0)
    class Plane:                # every data-plane counter 0
        def __getattr__(self, name):
            return 0
    plane = Plane()
    ep = SimpleNamespace(namespaces={("u", "a"): SimpleNamespace(session=live, interfaces={})}, plane=plane,
                         master=None, rosbridge=None,
                         budget=PartBudget(), parser=SimpleNamespace(parsed=0))
    m = Metrics(ep)
    m.session_ended(ended)
    text = generate_latest(m.registry).decode()
    assert "rce_robot_errors_total 2.0" in text and "rce_robot_queue_depth 1.0" in text
    assert "rce_robot_dropped_total 0.0" in text and "rce_robot_connections 1.0" in text


# -- to a robot that does not keep up: each interface's newest ------------------------------------
def dm_out(s: RobotSession, now: float | None = None, n: int | None = None) -> list:
    """(iTag, msg) of the DMs (and ("ST", status) of the STs) that go out now."""
    out = []
    for f in s.data_to_send(n, now):
        d = json.loads(f)
        out.append((d["data"]["iTag"], d["data"]["msg"]) if d["type"] == "DM" else ("ST", d["data"]["status"]))
    return out


def test_past_the_bound_the_busiest_interface_drops_its_oldest():
    s = RobotSession("r1", SessionLimits(queue_size=3))
    for i in range(3):
        s.send_dm("scan", "t", "", i, data=True)
    s.send_status({"topic": "node", "status": "up"})           # never dropped; control goes first
    s.send_dm("map", "t", "", "m0", data=True)                  # full: scan, the busiest, loses 0
    s.send_dm("scan", "t", "", 3, data=True)                    # full: scan (1, 2) loses 1
    assert s.dropped == 2 and s.out_data == 3 and s.outbox == 4
    assert dm_out(s) == [("ST", "up"), ("scan", 2), ("map", "m0"), ("scan", 3)]
    assert s.outbox == 0 and s.out_data == 0 and s.stats()["msgs_out"] == 4


def test_a_robot_that_never_reads_costs_a_bounded_outbox():
    s = RobotSession("r1", SessionLimits(queue_size=10))
    for i in range(10_000):
        s.send_dm("scan", "t", "", i, data=True)
    assert s.dropped == 9_990 and s.outbox == 10
    assert s.out.queue.places <= 2 * 10 + 1               # the dropped ones' places are reclaimed
    assert [m for _, m in dm_out(s)] == list(range(9_990, 10_000))


def test_a_message_older_than_max_lag_goes_only_when_nothing_newer_of_its_interface_waits():
    s = RobotSession("r1", SessionLimits(max_lag=1.0))
    s.send_dm("pose", "t", "", "p0", data=True, now=0.0)
    s.send_dm("map", "t", "", "m0", data=True, now=0.0)         # a sparse topic: its only message
    s.send_dm("pose", "t", "", "p1", data=True, now=0.5)
    s.send_dm("pose", "t", "", "p2", data=True, now=1.4)
    assert dm_out(s, now=2.0, n=1) == [("map", "m0")]          # p0 (2 s old, p1 behind it) is dropped first
    assert dm_out(s, now=2.0) == [("pose", "p2")]              # p1 (1.5 s, p2 behind it) too; p2 0.6 s
    assert s.dropped == s.expired == 2 and s.stats()["expired"] == 2 and s.outbox == 0
    s.send_dm("pose", "t", "", "p3", data=True, now=3.0)
    assert dm_out(s, now=60.0) == [("pose", "p3")]             # the newest goes out however late


def test_without_max_lag_age_drops_nothing():
    s = RobotSession("r1", SessionLimits(max_lag=None))
    s.send_dm("pose", "t", "", "p0", data=True, now=0.0)
    s.send_dm("pose", "t", "", "p1", data=True, now=0.1)
    assert dm_out(s, now=100.0) == [("pose", "p0"), ("pose", "p1")] and s.dropped == 0


def test_queue_size_below_one_is_refused():
    with pytest.raises(ValueError, match="queue_size must be >= 1"):
        RobotSession("r1", SessionLimits(queue_size=0))


def test_topic_data_goes_at_once_when_nothing_waits_exactly_as_through_the_queue():
    """``data_now`` (the endpoint's path when the robot's link takes frames now) gives the frames
    ``send_dm`` then ``data_to_send`` would, numbered and kept with resume, and counts the same; when
    anything waits, the DM queues behind it instead, in order."""
    def run(at_once: bool) -> tuple[list, dict]:
        s = RobotSession("r1", resume=ResumeOptions(token="t" * 32))
        s.add_interface("echo", "PublisherForwarder", "geometry_msgs/PoseStamped")
        frames = list(s.data_to_send())                         # ST session started
        for i in range(3):
            if at_once:
                out = s.data_now("echo", "geometry_msgs/PoseStamped", "", bytes([i]) * 4, now=float(i))
                assert out is not None
                frames += out
            else:
                s.send_dm("echo", "geometry_msgs/PoseStamped", "", bytes([i]) * 4, data=True, now=float(i))
                frames += s.data_to_send(None, float(i))
        st = s.stats()
        return ([json.loads(f) if isinstance(f, str) else f[ID_LEN:] for f in frames],
                {k: st[k] for k in ("msgs_out", "kept", "kept_bytes", "outbox", "dropped", "lanes")})
    now_frames, now_stats = run(True)
    queued_frames, queued_stats = run(False)
    strip = [{**f, "data": {k: v for k, v in f["data"].items() if k != "msg*"}} if isinstance(f, dict) else f
             for f in now_frames]
    assert strip == [{**f, "data": {k: v for k, v in f["data"].items() if k != "msg*"}} if isinstance(f, dict)
                     else f for f in queued_frames]                # part ids differ: fresh per part
    assert [f["seq"] for f in now_frames if isinstance(f, dict) and f["type"] == "DM"] == [1, 2, 3]
    assert now_stats == queued_stats and now_stats["lanes"]["state"]["sent"] == 3

    s = RobotSession("r1")
    s.add_interface("echo", "PublisherForwarder", "geometry_msgs/PoseStamped")
    s.send_status({"topic": "node", "status": "up"})             # waits: the DM goes behind it
    assert s.data_now("echo", "geometry_msgs/PoseStamped", "", b"p", now=0.0) is None
    out = frames_of(s)
    assert [f["type"] for f in out if isinstance(f, dict)] == ["ST", "DM"] and out[-1][ID_LEN:] == b"p"
    assert s.outbox == 0
