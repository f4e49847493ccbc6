"""``rce-ros --record run.mcap`` with ROS 2 classes: the robot's topics are ``std_msgs/msg/String`` (its end of the
Test package's ROS 1 echo node; the engine converts), recorded as MCAP's ROS 2 profile: message encoding ``cdr``
(the bytes as rclpy writes them), schema encoding ``ros2msg``, the channel's ``offered_qos_profiles`` from the
config's QoS. Read back with ``mcap``'s reader and decoded with a rosbags typestore built from the recorded schema
alone. And sans I/O: a file of ROS 1 and ROS 2 topics keeps each in its own encoding; a ROS 1 bag refuses CDR."""
from __future__ import annotations

import json
import os
import signal

import pytest
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import String

from rce.interfaces.qos import QoS
from rce.plumbing.errors import MessageError
from rce_client.bag import BagRecorder
from rce_client.mcap_recorder import McapRecorder, recorder_for

from .test_e2e_debug import BIN, CONFIG, Proc, tool

ROS2 = "std_msgs/msg/String"


def _ros2_config(url: str) -> dict:
    """The debug sample's echo, its robot-side topics in ROS 2's form (the container's stay ROS 1)."""
    cfg = json.loads(CONFIG.read_text())
    cfg.update(url=url, robotID="recordRos2Robot", parameters=[],
               nodes=[n for n in cfg["nodes"] if n["nTag"] == "strEcho"])
    cfg["interfaces"] = [i for i in cfg["interfaces"] if "Service" not in i["iType"] and i["iTag"] != "parameterTest"]
    for i in cfg["interfaces"]:
        if i["eTag"] == "testRobot":
            i.update(eTag="recordRos2Robot", iCls=ROS2)
            if i["iTag"] == "stringEchoResp":
                i["qos"] = "sensor_data"
    cfg["connections"] = [{"tagA": c["tagA"], "tagB": c["tagB"].replace("testRobot", "recordRos2Robot")}
                          for c in cfg["connections"] if "Service" not in c["tagA"] and "parameter" not in c["tagA"]]
    return cfg


async def test_rce_ros_records_ros2_topics_as_cdr(engine, tmp_path):
    from mcap.reader import make_reader
    (tmp_path / "ros2.config").write_text(json.dumps(_ros2_config(engine.master_url)))
    bus, mcap = str(tmp_path / "robot.sock"), tmp_path / "run.mcap"
    ros = await Proc.start(str(BIN / "rce-ros"), str(tmp_path / "ros2.config"), "--bus", bus, "--timeout", "60",
                           "--record", str(mcap), env=dict(os.environ, RCE_LOG_JSON="1"))
    try:
        await ros.wait_line(r"^rce-ros: ready \(2 interface\(s\) up", timeout=90)
        tool_env = dict(os.environ, RCE_BUS=bus)
        echo = await Proc.start(str(BIN / "rce-topic"), "echo", "/stringEchoResp", "-n", "2", env=tool_env)
        await echo.wait_line(r"^subscribed to /stringEchoResp", key="err")
        for word in ("hello", "world"):
            rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", ROS2, f"{{data: {word}}}", "--once",
                                    env=tool_env)
            assert rc == 0, err
        assert await echo.wait(30) == 0, echo.dump()
        ros.p.send_signal(signal.SIGINT)
        assert await ros.wait(30) == 0, ros.dump()
    finally:
        await ros.kill()
    assert "rce-ros: recorded 4 message(s) on 2 topic(s) to" in ros.text(), ros.dump()
    seen: dict[str, list[str]] = {}
    with open(mcap, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        for schema, channel, message in reader.iter_messages():
            assert (channel.message_encoding, schema.name, schema.encoding) == ("cdr", ROS2, "ros2msg")
            store = get_typestore(Stores.EMPTY)          # the recorded schema alone decodes the bytes
            store.register(get_types_from_msg(schema.data.decode(), schema.name))
            text = store.deserialize_cdr(message.data, ROS2).data
            assert message.data == serialize_message(String(data=text))      # CDR as rclpy writes it
            qos = channel.metadata["offered_qos_profiles"]
            assert ("reliability: best_effort" if channel.topic == "/stringEchoResp" else "reliability: reliable") \
                in qos and "depth: " in qos
            seen.setdefault(channel.topic, []).append(text)
    assert seen == {"/stringEchoReq": ["hello", "world"], "/stringEchoResp": ["hello", "world"]}


def test_ros1_and_ros2_topics_in_one_file(tmp_path):
    """Sans I/O: no profile for a mix; each channel in its class's encodings; a ROS 1 bag refuses a ROS 2 class."""
    from mcap.reader import make_reader
    rec = recorder_for(tmp_path / "mix.mcap", topics=[("/a", "std_msgs/String", None),
                                                      ("/b", ROS2, QoS(durability="transient_local", depth=1))])
    assert isinstance(rec, McapRecorder)
    rec.open()
    rec.write("/a", "std_msgs/String", b"\x02\x00\x00\x00hi", 1)
    rec.write("/b", ROS2, serialize_message(String(data="hi")), 2)
    with pytest.raises(MessageError, match="recorded as std_msgs/String"):
        rec.write("/a", ROS2, b"", 3)
    rec.close()
    with open(tmp_path / "mix.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == ""
        got = {c.topic: (c.message_encoding, s.encoding, s.name, c.metadata)
               for s, c, _ in reader.iter_messages()}
    assert got["/a"] == ("ros1", "ros1msg", "std_msgs/String", {})
    assert got["/b"][:3] == ("cdr", "ros2msg", ROS2)
    assert "durability: transient_local\n" in got["/b"][3]["offered_qos_profiles"]
    bag = BagRecorder(tmp_path / "x.bag")
    bag.open()
    with pytest.raises(MessageError, match="a ROS 1 bag holds ROS 1 messages"):
        bag.write("/b", ROS2, serialize_message(String(data="hi")))
    bag.close()
