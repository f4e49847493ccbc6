"""ROS 2 types in the message registry (CDR, the same bytes as rclpy's), ROS 1 <-> ROS 2 conversion,
and the config's actions and QoS: sans I/O, against rclpy's own serialization where bytes matter."""
from __future__ import annotations

import uuid

import pytest
from rclpy.serialization import deserialize_message, serialize_message

from rce.interfaces import actions
from rce.interfaces.classes import is_ros2_name, same_type
from rce.interfaces.qos import QoS, parse_qos
from rce.messages import MessageRegistry
from rce.messages.convert import conversion, converter
from rce.plumbing.errors import ConfigError, MessageError
from rce.protocol.config import parse_config


@pytest.fixture(scope="module")
def reg() -> MessageRegistry:
    return MessageRegistry()


def test_names():
    assert is_ros2_name("std_msgs/msg/String") and is_ros2_name("/std_srvs/srv/Trigger")
    assert is_ros2_name("test_msgs/action/Fibonacci") and not is_ros2_name("std_msgs/String")
    assert same_type("std_msgs/String", "std_msgs/msg/String") and same_type("Test/Echo", "Test/srv/Echo")
    assert not same_type("std_msgs/String", "std_msgs/msg/Bool")


def test_cdr_is_rclpy_bytes(reg):
    from geometry_msgs.msg import PoseStamped
    from std_msgs.msg import String
    t = reg.msg_type("std_msgs/msg/String")
    assert t == "ros2:std_msgs/msg/String"
    assert reg.json_to_bytes(t, {"data": "héllo"}) == serialize_message(String(data="héllo"))
    pose = PoseStamped()
    pose.header.frame_id, pose.header.stamp.sec, pose.pose.position.x, pose.pose.orientation.w = "map", 7, 1.5, 1.0
    raw = serialize_message(pose)
    got = reg.bytes_to_json(reg.msg_type("geometry_msgs/msg/PoseStamped"), raw)
    assert got["header"]["frame_id"] == "map" and got["pose"]["position"]["x"] == 1.5
    back = reg.json_to_bytes(reg.msg_type("geometry_msgs/msg/PoseStamped"), got)
    assert deserialize_message(back, PoseStamped) == pose


def test_services_and_action_parts_from_share(reg):
    from test_msgs.action import Fibonacci
    req_t, resp_t = reg.srv_types("std_srvs/srv/Trigger")
    assert reg.bytes_to_json(req_t, reg.json_to_bytes(req_t, {})) == {}      # an empty request is {}, as in ROS 2
    assert reg.bytes_to_json(resp_t, reg.json_to_bytes(resp_t, {"success": True, "message": "ok"})) == \
        {"success": True, "message": "ok"}
    goal = Fibonacci.Impl.SendGoalService.Request()
    goal.goal.order, goal.goal_id.uuid = 9, list(uuid.uuid4().bytes)
    send_req, _ = reg.srv_types("test_msgs/action/Fibonacci_SendGoal")
    assert reg.bytes_to_json(send_req, serialize_message(goal))["goal"] == {"order": 9}
    fb = Fibonacci.Impl.FeedbackMessage()
    fb.feedback.sequence = [0, 1, 1, 2]
    assert reg.bytes_to_json(reg.msg_type("test_msgs/action/Fibonacci_FeedbackMessage"),
                             serialize_message(fb))["feedback"] == {"sequence": [0, 1, 1, 2]}
    _, result_resp = reg.srv_types("test_msgs/action/Fibonacci_GetResult")
    res = Fibonacci.Impl.GetResultService.Response(status=4)
    assert reg.bytes_to_json(result_resp, serialize_message(res))["status"] == 4
    reg.srv_types("action_msgs/srv/CancelGoal")
    reg.msg_type("action_msgs/msg/GoalStatusArray")


@pytest.mark.parametrize("call, cls, match", [
    ("msg_type", "nope_msgs/msg/X", "unknown ROS 2 message class 'nope_msgs/msg/X'"),
    ("srv_types", "std_srvs/srv/Nope", "unknown ROS 2 service class 'std_srvs/srv/Nope'"),
    ("msg_type", "std_srvs/srv/Trigger", "is a ROS 2 service, not a message class"),
    ("srv_types", "std_msgs/msg/String", "is not a ROS 2 service class"),
])
def test_unknown_types_are_named(reg, call, cls, match):
    with pytest.raises(MessageError, match=match):
        getattr(reg, call)(cls)


def test_undecodable_cdr_is_named(reg):
    t = reg.msg_type("std_msgs/msg/String")
    with pytest.raises(MessageError, match="not CDR of std_msgs/msg/String"):
        reg.check_structure(t, b"hello")
    with pytest.raises(MessageError, match="do not deserialize as std_msgs/msg/String"):
        reg.check_structure(t, b"\x00\x01\x00\x00\xff\xff\xff\x7f")


def test_ros1_ros2_conversion(reg):
    ros1, ros2 = reg.msg_type("sensor_msgs/LaserScan"), reg.msg_type("sensor_msgs/msg/LaserScan")
    scan = {"header": {"seq": 12, "stamp": {"secs": 3, "nsecs": 5}, "frame_id": "laser"}, "ranges": [1.0, 2.5],
            "range_max": 8.0}
    cdr = converter(reg, ros1, ros2)(reg.json_to_bytes(ros1, scan))
    from sensor_msgs.msg import LaserScan
    m = deserialize_message(cdr, LaserScan)       # rclpy reads what the conversion wrote
    assert (m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec, list(m.ranges), m.range_max) == \
        ("laser", 3, 5, [1.0, 2.5], 8.0)
    back = reg.bytes_to_json(ros1, converter(reg, ros2, ros1)(cdr))
    assert back["header"] == {"seq": 0, "stamp": {"secs": 3, "nsecs": 5}, "frame_id": "laser"}   # ROS 2 has no seq
    with pytest.raises(MessageError, match="cannot convert"):
        converter(reg, ros1, ros2)(b"\x01")


def test_service_conversion_both_halves(reg):
    reg.register_srv("std_srvs/Trigger", "---\nbool success\nstring message")     # ROS 1's, as a package brings it
    conv = conversion(reg, "ServiceProvider", "std_srvs/srv/Trigger", "std_srvs/Trigger")
    ros1_req = conv.out(reg.json_to_bytes(reg.srv_types("std_srvs/srv/Trigger")[0], {}))
    assert ros1_req == b""                       # std_srvs/Trigger's request is empty in ROS 1
    ros1_resp = reg.json_to_bytes(reg.srv_types("std_srvs/Trigger")[1], {"success": True, "message": "hi"})
    assert reg.bytes_to_json(reg.srv_types("std_srvs/srv/Trigger")[1], conv.back(ros1_resp)) == \
        {"success": True, "message": "hi"}
    with pytest.raises(MessageError, match="not the same type"):
        conversion(reg, "Subscriber", "std_msgs/msg/String", "std_msgs/Bool")


BASE = {"url": "http://127.0.0.1:9000/", "userID": "u", "password": "p", "robotID": "r", "containers": [{"cTag": "c"}]}


def test_action_entries_become_five_parts():
    cfg = parse_config({**BASE, "interfaces": [
        {"eTag": "r", "iTag": "fib", "iType": "ActionProviderForwarder", "iCls": "test_msgs/action/Fibonacci",
         "addr": "/fibonacci"},
        {"eTag": "c", "iTag": "fib", "iType": "ActionClientInterface", "iCls": "test_msgs/action/Fibonacci"}],
        "connections": [{"tagA": "r/fib", "tagB": "c/fib"}]})
    robot = {i.iTag: i for i in cfg.interfaces if i.eTag == "r"}
    assert robot["fib.send_goal"].iType == "ServiceProviderForwarder"
    assert robot["fib.send_goal"].iCls == "test_msgs/action/Fibonacci_SendGoal"
    assert robot["fib.send_goal"].addr == "/fibonacci/_action/send_goal"
    assert robot["fib.feedback"].iType == "PublisherForwarder"
    assert robot["fib.status"].qos.durability == "transient_local"
    assert robot["fib.cancel_goal"].iCls == "action_msgs/srv/CancelGoal" and robot["fib.cancel_goal"].action == "fib"
    cloud = {i.iTag: i for i in cfg.interfaces if i.eTag == "c"}
    assert cloud["fib.get_result"].iType == "ServiceClientInterface"
    assert cloud["fib.status"].iType == "SubscriberInterface"
    assert cloud["fib.get_result"].addr == "/fib/_action/get_result"
    assert [c.tagA for c in cfg.connections][:2] == ["r/fib.feedback", "r/fib.status"]    # topics wired first
    assert sorted((c.tagA, c.tagB) for c in cfg.connections) == sorted(
        (f"r/fib.{p}", f"c/fib.{p}") for p in ("send_goal", "get_result", "cancel_goal", "feedback", "status"))
    assert "qos" not in robot["fib.status"].component() and "action" not in robot["fib.status"].component()
    assert actions.call_timeout("test_msgs/action/Fibonacci_GetResult") == actions.RESULT_TIMEOUT
    assert actions.call_timeout("std_srvs/srv/Trigger") == actions.SERVICE_TIMEOUT
    # a goal waits for its action's feedback and status to be matched; no other call waits
    assert actions.goal_topics("/nav/fib/_action/send_goal") == ("/nav/fib/_action/feedback", "/nav/fib/_action/status")
    assert actions.goal_topics("/nav/fib/_action/get_result") == () == actions.goal_topics("/add_two_ints")


def test_action_entry_with_a_message_class_is_refused():
    with pytest.raises(ConfigError, match=r"interfaces\[0\].iCls: .*'pkg/action/Type', got 'std_msgs/msg/String'"):
        parse_config({**BASE, "interfaces": [{"eTag": "r", "iTag": "a", "iType": "ActionClientForwarder",
                                              "iCls": "std_msgs/msg/String"}]})


def test_qos():
    assert parse_qos(None) == QoS() and parse_qos("sensor_data") == QoS(reliability="best_effort", depth=5)
    assert parse_qos({"profile": "map", "depth": 3}) == QoS(durability="transient_local", depth=3)
    for bad, match in (({"depth": 0}, "qos.depth"), ("fast", "qos.profile"), ({"reliability": "x"}, "qos.reliability"),
                       ({"lifespan": 1}, "unknown key")):
        with pytest.raises(ValueError, match=match):
            parse_qos(bad)
    with pytest.raises(ConfigError, match=r"interfaces\[0\].qos: qos.durability"):
        parse_config({**BASE, "interfaces": [{"eTag": "r", "iTag": "s", "iType": "SubscriberForwarder",
                                              "iCls": "std_msgs/msg/String", "qos": {"durability": "forever"}}]})
