"""Robot configs of the fleet (the seed paper's ``robot1.config`` format, section III-C-2).

``robot_config(n)`` is the config of simulated robot ``RobotN``; ``examples/fleet/configs/robot1.config``
... ``examples/fleet/configs/robot10.config`` are its output (``rce-fleet configs`` rewrites them;
``tests/fleet/test_fleet_e2e.py`` checks they match). The fleet manager
(:mod:`rce_fleet.live.manager`, robotID ``fleetManager``) creates the fleet container
``cTag_01`` and the global planner before the robots connect, so a robot's config adds
only its own move_client node, interfaces and connections to that container:

================================  ================================  =====================================
container side (eTag cTag_01)     robot side (eTag RobotN)          topic, class
================================  ================================  =====================================
amclPoseReceiver_N  Publisher     amclPoseSender_N  SubscriberFwd   /RobotN/amcl_pose <- /amcl_pose,
                    Interface                                       geometry_msgs/PoseWithCovarianceStamped
obstaclesReceiver_N Publisher     obstaclesSender_N SubscriberFwd   /RobotN/obstacles <- /obstacles,
                    Interface                                       geometry_msgs/PoseArray
goalSender_N  SubscriberInterface goalReceiver_N  PublisherFwd      /RobotN/move_base_simple/goal ->
                                                                    /move_base_simple/goal, PoseStamped
cancelSender_N SubscriberInterface cancelReceiver_N PublisherFwd    /RobotN/move_base/cancel ->
                                                                    /move_base/cancel, actionlib_msgs/GoalID
================================  ================================  =====================================

Robot-side interfaces are Forwarders (the serialized ROS message as a binary part: no JSON
on the robot's side); the robot's local topics carry the names a TurtleBot's ``amcl`` and
``move_base`` use.

``robot_config(n, placement=...)`` (``rce-fleet demo --edge-hosts``) gives the move_client a
container of its own, ``mc_RobotN``, which the placer places (``auto``) or which stays on the
robot's own computer (``robot``): the robot's pose goes to both containers, its goals and cancels
come from ``mc_RobotN``, and the planner's paths, clearances and cancels
(``/RobotN/goalNodesList``, ``/RobotN/clearance``, ``/RobotN/cancelGoal``) and the move_client's
``/RobotN/progress`` cross between the two containers through container-to-container connections
(docs/placement.md).

``ros2_config(cfg)`` is the config of the same robot as a ROS 2 robot (``rce-fleet demo --ros2``,
``rce-ros CONFIG --ros2``): its robot-side interfaces name their classes in ROS 2's form
(``geometry_msgs/msg/PoseStamped``, ``actionlib_msgs/msg/GoalID``, ``sensor_msgs/msg/BatteryState``) at
the same topics, and the cloud's ends keep their ROS 1 classes: the engine converts, the sending end.
"""
from __future__ import annotations

import json
from pathlib import Path

__all__ = ["robot_config", "ros2_config", "write_configs", "FLEET_CTAG", "DEFAULT_URL", "USER", "PASSWORD"]

FLEET_CTAG = "cTag_01"
DEFAULT_URL = "http://127.0.0.1:9000/"
USER = "testUser"
PASSWORD = "testUser"

# (container iTag, container iType, robot iTag, robot iType, class, container addr, robot addr)
_LINKS = [
    ("amclPoseReceiver_{n}", "PublisherInterface", "amclPoseSender_{n}", "SubscriberForwarder",
     "geometry_msgs/PoseWithCovarianceStamped", "/Robot{n}/amcl_pose", "/amcl_pose"),
    ("obstaclesReceiver_{n}", "PublisherInterface", "obstaclesSender_{n}", "SubscriberForwarder",
     "geometry_msgs/PoseArray", "/Robot{n}/obstacles", "/obstacles"),
    ("goalSender_{n}", "SubscriberInterface", "goalReceiver_{n}", "PublisherForwarder",
     "geometry_msgs/PoseStamped", "/Robot{n}/move_base_simple/goal", "/move_base_simple/goal"),
    ("cancelSender_{n}", "SubscriberInterface", "cancelReceiver_{n}", "PublisherForwarder",
     "actionlib_msgs/GoalID", "/Robot{n}/move_base/cancel", "/move_base/cancel"),
]


# between the fleet container (planner) and a move_client's own container: (iTag, class, topic, from the planner?)
_PLANNER_LINKS = [
    ("goalNodesList", "std_msgs/Int32MultiArray", "/Robot{n}/goalNodesList", True),
    ("clearance", "fleet/Clearance", "/Robot{n}/clearance", True),
    ("cancelGoal", "std_msgs/Bool", "/Robot{n}/cancelGoal", True),
    ("progress", "fleet/MoveProgress", "/Robot{n}/progress", False),
]
MOVE_CLIENT_DEADLINE_MS = 200    # a move_client answers a pose within this (its control loop's period: 5 Hz)


def robot_config(index: int, url: str = DEFAULT_URL, user: str = USER, password: str = PASSWORD,
                 ctag: str = FLEET_CTAG, placement: str | None = None, params: dict | None = None) -> dict:
    """The config of robot ``Robot<n>`` (a dict in the seed's JSON format). ``placement``
    (``auto``, ``robot``, ``cloud``): the move_client runs in a container of its own, ``mc_Robot<n>``,
    placed so (module doc), with the parameters ``params`` (name -> value: the grid it reads); None:
    in the fleet container ``ctag``."""
    rid = f"Robot{index}"
    mc = f"mc_{rid}" if placement else ctag
    interfaces, connections = [], []
    for c_tag, c_type, r_tag, r_type, cls, c_addr, r_addr in _LINKS:
        c_tag, r_tag, c_addr = c_tag.format(n=index), r_tag.format(n=index), c_addr.format(n=index)
        # the planner reads poses and obstacles; the move_client reads poses and sends goals and cancels
        ends = [ctag] if c_tag.startswith("obstacles") else [mc] if c_type == "SubscriberInterface" else \
            sorted({ctag, mc})
        for e in ends:
            interfaces.append({"eTag": e, "iTag": c_tag, "iType": c_type, "iCls": cls, "addr": c_addr})
            connections.append({"tagA": f"{e}/{c_tag}", "tagB": f"{rid}/{r_tag}"})
        interfaces.append({"eTag": rid, "iTag": r_tag, "iType": r_type, "iCls": cls, "addr": r_addr})
    containers = []
    if placement:
        containers.append({"cTag": mc, "placement": placement, "robot": rid, "deadline_ms": MOVE_CLIENT_DEADLINE_MS,
                           "consumes": [f"amclPoseSender_{index}"]})
        for tag, cls, addr, from_planner in _PLANNER_LINKS:
            addr = addr.format(n=index)
            out, into = (ctag, mc) if from_planner else (mc, ctag)
            interfaces.append({"eTag": out, "iTag": f"{tag}Out_{index}", "iType": "SubscriberInterface", "iCls": cls,
                               "addr": addr})
            interfaces.append({"eTag": into, "iTag": f"{tag}In_{index}", "iType": "PublisherInterface", "iCls": cls,
                               "addr": addr})
            connections.append({"tagA": f"{out}/{tag}Out_{index}", "tagB": f"{into}/{tag}In_{index}"})
    return {
        "url": url, "userID": user, "password": password, "robotID": rid,
        "containers": containers,
        "nodes": [{"cTag": mc, "nTag": f"move_client_node_{index}", "pkg": "fleet", "exe": "move_client",
                   "args": f"--robot {rid}", "namespace": rid}],
        "parameters": [{"cTag": mc, "name": k, "value": v} for k, v in (params or {}).items()] if placement else [],
        "interfaces": interfaces,
        "connections": connections,
    }


def ros2_class(cls: str) -> str:
    """A message class in ROS 2's form: ``pkg/Type`` -> ``pkg/msg/Type`` (one already so is kept)."""
    parts = cls.strip("/").split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else cls


def ros2_config(cfg: dict) -> dict:
    """A copy of robot config ``cfg`` (:func:`robot_config`'s, with any interfaces added to it) whose
    robot-side interfaces (eTag = its robotID) name their classes in ROS 2's form (:func:`ros2_class`);
    the others are kept."""
    rid = cfg["robotID"]
    return cfg | {"interfaces": [it | {"iCls": ros2_class(it["iCls"])} if it["eTag"] == rid else dict(it)
                                 for it in cfg["interfaces"]]}


def dumps(cfg: dict) -> str:
    """The config as the committed files have it: JSON, one interface/connection a line."""
    lines = ["{"]
    for k in ("url", "userID", "password", "robotID"):
        lines.append(f"    {json.dumps(k)}: {json.dumps(cfg[k])},")
    for k in ("containers", "nodes", "parameters", "interfaces", "connections"):
        items = cfg[k]
        if not items:
            lines.append(f"    {json.dumps(k)}: [],")
            continue
        lines.append(f"    {json.dumps(k)}: [")
        lines += [f"        {json.dumps(it)}," for it in items[:-1]] + [f"        {json.dumps(items[-1])}"]
        lines.append("    ],")
    lines[-1] = lines[-1].rstrip(",")
    lines.append("}")
    return "\n".join(lines) + "\n"


def write_configs(directory: str | Path, robots: int, url: str = DEFAULT_URL) -> list[Path]:
    """Write ``robot1.config`` ... ``robot<robots>.config`` into ``directory``; returns the paths."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for n in range(1, robots + 1):
        p = d / f"robot{n}.config"
        p.write_text(dumps(robot_config(n, url)))
        out.append(p)
    return out
