"""Lanes, sans I/O: an interface's lane from its type and size, or as set; a bad lane is refused
naming where it was."""
from __future__ import annotations

import pytest

from rce.plumbing.errors import ProtocolError
from rce.protocol import schema
from rce.protocol.lanes import BULK_SIZE, Lane, default_lane, interface_lane, message_lane, parse_lane
from rce.protocol.session import RobotSession


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
    assert schema.parse(_cn("state"))[1].addInterfaces[0].lane is Lane.STATE
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
