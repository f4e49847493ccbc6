"""Lanes, sans I/O: an interface's lane from its type and size, or as set; a bad lane is refused
naming where it was."""
from __future__ import annotations

import json

import pytest

from rce.plumbing.errors import ProtocolError
from rce.protocol import schema
from rce.protocol.events import Deliver
from rce.protocol.frames import encode
from rce.protocol.lane_queue import LaneQueues
from rce.interfaces.pacer import Pacer, chunks, parse_rate
from rce.interfaces.lanes import BULK_SIZE, Lane, default_lane, interface_lane, message_lane, parse_lane
from rce.protocol.robot_session import LANES_STATUS_EVERY
from rce.protocol.session import ResumeOptions, RobotSession
from rce_robot.rosbridge.outbox import RosbridgeOutbox


@pytest.mark.parametrize("cls, service, lane", [
    ("std_msgs/String", False, Lane.CONTROL), ("std_msgs/Bool", False, Lane.CONTROL),
    ("/std_msgs/Int32MultiArray", False, Lane.CONTROL), ("actionlib_msgs/GoalID", False, Lane.CONTROL),
    ("move_base_msgs/MoveBaseActionGoal", False, Lane.CONTROL), ("geometry_msgs/Twist", False, Lane.CONTROL),
    ("Test/StringEcho", True, Lane.CONTROL), ("std_srvs/Trigger", True, Lane.CONTROL),
    ("geometry_msgs/PoseStamped", False, Lane.STATE), ("geometry_msgs/PoseWithCovarianceStamped", False, Lane.STATE),
    ("nav_msgs/Odometry", False, Lane.STATE), ("tf2_msgs/TFMessage", False, Lane.STATE),
    ("tf/tfMessage", False, Lane.STATE), ("move_base_msgs/MoveBaseActionFeedback", False, Lane.STATE),
    ("fleet/FleetState", False, Lane.STATE),
    ("sensor_msgs/Image", False, Lane.BULK), ("sensor_msgs/msg/CompressedImage", False, Lane.BULK),
    ("sensor_msgs/PointCloud2", False, Lane.BULK), ("sensor_msgs/LaserScan", False, Lane.BULK),
    ("nav_msgs/OccupancyGrid", False, Lane.BULK), ("nav_msgs/GetMap", True, Lane.BULK),
])
def test_the_default_lane_comes_from_the_message_type(cls, service, lane):
    assert default_lane(cls, service) is lane
    assert interface_lane(cls, service) is lane


def test_a_lane_set_wins_and_big_messages_of_a_default_lane_go_bulk():
    assert interface_lane("sensor_msgs/Image", False, "control") is Lane.CONTROL
    assert message_lane(Lane.CONTROL, False, BULK_SIZE) is Lane.CONTROL
    assert message_lane(Lane.CONTROL, False, BULK_SIZE + 1) is Lane.BULK
    assert message_lane(Lane.STATE, False, 10 * BULK_SIZE) is Lane.BULK
    assert message_lane(Lane.CONTROL, True, 10 * BULK_SIZE) is Lane.CONTROL     # set by the robot: kept
    assert [lane.rank for lane in Lane] == [0, 1, 2]


@pytest.mark.parametrize("value", ["fast", "", 3, None, ["bulk"]])
def test_a_bad_lane_is_refused_naming_where_and_the_lanes(value):
    with pytest.raises(ProtocolError) as ei:
        parse_lane(value, "interfaces[2].lane")
    assert ei.value.message.startswith("interfaces[2].lane: unknown lane ")
    assert "expected one of 'control', 'state', 'bulk'" in ei.value.message
    assert parse_lane("BULK") is Lane.BULK


def _cn(lane) -> dict:
    return {"type": "CN", "data": {"addInterfaces": [{"endpointTag": "r", "interfaceTag": "cam",
                                                      "interfaceType": "SubscriberForwarder",
                                                      "className": "sensor_msgs/Image", "lane": lane}]}}


def test_the_wire_takes_a_lane_per_interface_and_refuses_a_bad_one():
    assert schema.validate(_cn("state"))[1].addInterfaces[0].lane is Lane.STATE
    with pytest.raises(ProtocolError, match=r"CN\.data\.addInterfaces\[0\]\.lane: unknown lane 'slow'"):
        schema.validate(_cn("slow"))


def test_the_session_knows_each_interfaces_lane():
    s = RobotSession("r")
    s.add_interface("cam", "PublisherForwarder", "sensor_msgs/Image")
    s.add_interface("odom", "PublisherConverter", "nav_msgs/Odometry")
    s.add_interface("cancel", "PublisherForwarder", "std_msgs/String")
    s.add_interface("pinned", "PublisherForwarder", "std_msgs/String", Lane.CONTROL)
    assert s.lane_of("cam") is Lane.BULK and s.lane_of("odom", {"pose": {}}) is Lane.STATE
    assert s.lane_of("cancel", b"x" * 100) is Lane.CONTROL
    assert s.lane_of("cancel", b"x" * (BULK_SIZE + 1)) is Lane.BULK
    assert s.lane_of("pinned", b"x" * (BULK_SIZE + 1)) is Lane.CONTROL
    s.remove_interface("cam")
    assert s.lane_of("cam") is Lane.STATE


# -- scheduling: strict priority with a minimum share -----------------------------------------------
def test_lanes_go_by_strict_priority_and_a_waiting_lower_lane_gets_one_turn_in_eight():
    q = LaneQueues(queue_size=100, starve_after=7)
    for i in range(20):
        q.put_data("cam", f"b{i}", 0.0, Lane.BULK)
    for i in range(20):
        q.put(f"c{i}", 0.0, Lane.CONTROL)
    got = [q.take(1.0) for _ in range(40)]
    lanes = [lane for lane, _ in got]
    assert lanes[:7] == [Lane.CONTROL] * 7 and lanes[7] is Lane.BULK          # bulk's reserved turn
    assert lanes[:16].count(Lane.BULK) == 2                                  # one in eight while both wait
    assert [item for lane, item in got if lane is Lane.CONTROL] == [f"c{i}" for i in range(20)]   # in order
    assert [item for lane, item in got if lane is Lane.BULK] == [f"b{i}" for i in range(20)]
    assert q.take(2.0) is None
    assert q.stats[Lane.CONTROL].taken == 20 and q.stats[Lane.BULK].delay_max == 1.0


def test_a_lane_left_alone_goes_at_once_and_control_is_never_dropped():
    q = LaneQueues(queue_size=2)
    for i in range(5):
        q.put(f"c{i}", 0.0)                          # control: never dropped
        q.put_data("scan", i, 0.0, Lane.BULK)        # bulk: the newest two kept
    assert q.waiting((Lane.CONTROL,)) == 5 and q.waiting((Lane.BULK,)) == 2 and q.dropped == 3
    assert q.take(0.0, (Lane.BULK,)) == (Lane.BULK, 3)      # a link that carries only bulk
    q.sent(Lane.BULK, 1000)
    stats = q.lane_stats()
    assert stats["bulk"]["sent"] == 1 and stats["bulk"]["bytes"] == 1000 and stats["bulk"]["dropped"] == 3
    assert stats["control"]["waiting"] == 5 and stats["state"]["taken"] == 0


# -- pacing and frames --------------------------------------------------------------------------------
def test_the_pacer_lets_a_burst_out_then_holds_bulk_to_its_rate():
    p = Pacer(rate=1_000_000, burst=64 * 1024)
    now = 0.0
    sent = 0
    while now < 1.0:
        wait = p.delay(BULK_SIZE, now)
        now += wait
        p.spend(BULK_SIZE, now)
        sent += BULK_SIZE
    assert 1_000_000 <= sent <= 1_000_000 + 64 * 1024 + BULK_SIZE     # the rate over 1 s, plus the burst
    assert p.delay(BULK_SIZE, now) > 0
    big = Pacer(rate=1000, burst=100)
    assert big.delay(5000, 0.0) == 0.0            # larger than the burst: waits for a full bucket only ...
    big.spend(5000, 0.0)
    assert big.delay(1, 0.0) == pytest.approx(4.901)   # ... and the debt holds the next bytes back


def test_rates_are_bytes_per_second_or_bits_with_a_unit():
    assert parse_rate("1250000") == 1_250_000 and parse_rate("10Mbit") == 1_250_000
    assert parse_rate("1.25MB") == 1_250_000 and parse_rate("10 mbit/s") == 1_250_000
    assert parse_rate("64KiB") == 65536
    for bad in ("fast", "10 furlongs", "0", "-5MB"):
        with pytest.raises(ValueError, match="rate"):
            parse_rate(bad)
    with pytest.raises(ValueError):
        Pacer(0)


def test_chunks_cut_a_message_into_frames_of_at_most_16_kib():
    data = bytes(range(256)) * 300                 # 76,800 bytes
    parts = list(chunks(data))
    assert [len(p) for p in parts] == [BULK_SIZE] * 4 + [76_800 - 4 * BULK_SIZE]
    assert b"".join(parts) == data and [len(p) for p in chunks(b"")] == [0]


# -- the bulk link of a robot session -----------------------------------------------------------------
def test_a_bulk_link_takes_bulk_topic_data_unnumbered_and_control_stays_on_the_session_link():
    s = RobotSession("r", resume=ResumeOptions())
    s.data_to_send()                                # ST session started
    s.add_interface("cam", "PublisherForwarder", "sensor_msgs/Image")
    s.add_interface("cancel", "PublisherConverter", "std_msgs/String")
    s.add_interface("map", "ServiceClientForwarder", "nav_msgs/GetMap")
    s.attach_bulk()
    s.send_dm("cam", "sensor_msgs/Image", "", b"frame", data=True, now=0.0)
    s.send_dm("cancel", "std_msgs/String", "", {"data": "stop"}, data=True, now=0.0)
    s.send_dm("map", "nav_msgs/GetMap", "m1", b"req", now=0.0)       # a call: never dropped, on the session link
    assert s.outbox == 2 and s.bulk_outbox == 1
    link = [json.loads(f) for f in s.data_to_send(now=0.0) if isinstance(f, str)]
    assert [(m["data"]["iTag"], m["seq"]) for m in link] == [("cancel", 1), ("map", 2)]
    text, part = s.bulk_to_send(0.0)
    assert json.loads(text)["data"]["iTag"] == "cam" and "seq" not in json.loads(text) and part.endswith(b"frame")
    s.detach_bulk()                                  # the bulk link dropped: bulk goes on the session link
    s.send_dm("cam", "sensor_msgs/Image", "", b"f2", data=True, now=1.0)
    assert s.bulk_outbox == 0 and s.outbox == 1 and s.bulk_to_send(1.0) is None


def test_the_robot_sends_dms_on_its_bulk_link_and_nothing_else():
    s = RobotSession("r", resume=ResumeOptions())
    s.add_interface("cam", "SubscriberForwarder", "sensor_msgs/Image")
    s.attach_bulk()
    s.data_to_send()
    text, part = encode({"type": "DM", "data": {"iTag": "cam", "type": "sensor_msgs/Image", "msg": b"img"}})
    s.receive_bulk(part[0], 0.0)                     # the part first: either order, as on the session link
    s.receive_bulk(text, 0.0)
    s.receive_bulk(encode({"type": "CC", "data": {"containerTag": "c"}})[0], 0.0)
    s.receive_bulk(encode({"type": "DM", "seq": 1, "data": {"iTag": "cam", "type": "sensor_msgs/Image",
                                                            "msg": "x"}})[0], 0.0)
    delivered = [e for e in s.events_received() if isinstance(e, Deliver)]
    assert [bytes(e.data["msg"]) for e in delivered] == [b"img"] and s.stats()["bulk_in"] == 1
    errors = [json.loads(f)["data"] for f in s.data_to_send() if isinstance(f, str) and '"ER"' in f]
    assert len(errors) == 2 and all("bulk link: carries unnumbered DMs only" in e for e in errors)
    assert s.incoming.last == 0                      # nothing on the bulk link is numbered


def test_a_rosbridge_client_gets_control_before_state_before_bulk_on_its_one_websocket():
    o = RosbridgeOutbox(size=4)
    for i in range(3):
        o.op({"op": "publish", "topic": "/cam", "msg": {"i": i}}, key=("/cam", "s1"), lane=Lane.BULK)
    o.op({"op": "publish", "topic": "/odom", "msg": {}}, key=("/odom", "s2"), lane=Lane.STATE)
    o.op({"op": "status", "level": "error", "msg": "bad op"})                  # never dropped: control
    got = []
    while not o.empty():
        op = json.loads(o.get_nowait()[0])
        got.append(op.get("topic", op["op"]))
    assert got == ["status", "/odom", "/cam", "/cam", "/cam"]
    assert o.queue.lane_stats()["bulk"]["sent"] == 3 and o.dropped == 0


def test_a_robot_with_a_bulk_link_is_told_its_lanes_counters_every_few_seconds():
    s = RobotSession("r")
    s.tick(0.0)
    assert s.data_to_send() == []                    # one link: no ST lanes (a 2013 client never gets one)
    s.attach_bulk()
    s.send_dm("x", "std_msgs/String", "", {"data": "stop"}, data=True, now=0.0)
    s.data_to_send(now=0.5)
    s.tick(1.0)
    s.tick(2.0)                                      # not again before LANES_STATUS_EVERY s
    st = [json.loads(f)["data"] for f in s.data_to_send()]
    assert len(st) == 1 and st[0]["topic"] == "lanes"
    assert st[0]["lanes"]["state"]["sent"] == 1 and st[0]["lanes"]["state"]["delay_max_s"] == 0.5
    s.tick(1.0 + LANES_STATUS_EVERY)
    assert json.loads(s.data_to_send()[0])["data"]["topic"] == "lanes"
