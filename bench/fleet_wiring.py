"""The wiring of the fleet load's robots (:mod:`fleet_load`), shared with its transport floor
(:mod:`fleet_floor`): each lightweight robot's interfaces, connections and robot-side iTags.

A robot ``RobotN`` is wired as the fleet demo's robot ``N`` (:func:`rce_fleet.configs.robot_config`)
for its pose, plus an echo of its pose and the planner's outputs it takes directly (:data:`DOWN`).
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

if importlib.util.find_spec("rce_fleet") is None:    # a checkout without the project installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "fleet"))

POSE = "geometry_msgs/PoseWithCovarianceStamped"
CTAG = "cTag_01"
ECHO_SUFFIX = "_echo"
# the planner's outputs a lightweight robot takes directly: (topic under /RobotN/, class)
DOWN = [("goalNodesList", "std_msgs/Int32MultiArray"), ("cancelGoal", "std_msgs/Bool"),
        ("clearance", "fleet/Clearance")]


def robot_wiring(n: int, side: str) -> tuple[list[dict], list[dict], dict]:
    """CN addInterfaces and CX connect items of robot ``n``, and its robot-side iTags by role.

    The pose link is the fleet robot's own (rce_fleet.configs.robot_config); the others take
    the planner's outputs and the echo the same way (container SubscriberInterface -> robot
    Publisher<side>)."""
    from rce_fleet.configs import robot_config
    rid = f"Robot{n}"
    cfg = robot_config(n)
    pose = [i for i in cfg["interfaces"] if i["iCls"] == POSE]
    links = []
    c_pose = next(i for i in pose if i["eTag"] == CTAG)
    r_pose = next(i for i in pose if i["eTag"] == rid)
    links.append((c_pose["iTag"], c_pose["iType"], r_pose["iTag"], r_pose["iType"].replace("Forwarder", side),
                  POSE, c_pose["addr"]))
    for topic, cls in [("amcl_pose" + ECHO_SUFFIX, POSE)] + DOWN:
        base = "poseEcho" if topic.startswith("amcl_pose") else topic
        links.append((f"{base}Sender_{n}", "SubscriberInterface", f"{base}Receiver_{n}", f"Publisher{side}",
                      cls, f"/{rid}/{topic}"))
    adds, conns = [], []
    for c_tag, c_type, r_tag, r_type, cls, addr in links:
        adds.append({"endpointTag": CTAG, "interfaceTag": c_tag, "interfaceType": c_type, "className": cls,
                     "addr": addr})
        adds.append({"endpointTag": rid, "interfaceTag": r_tag, "interfaceType": r_type, "className": cls})
        conns.append({"tagA": f"{CTAG}/{c_tag}", "tagB": f"{rid}/{r_tag}"})
    roles = {"pose": links[0][2], "echo": links[1][2], **{t: links[2 + k][2] for k, (t, _) in enumerate(DOWN)}}
    return adds, conns, roles


def echo_tags(n: int, side: str) -> tuple[str, str]:
    """Robot ``n``'s robot-side pose and echo iTags (:func:`robot_wiring`)."""
    roles = robot_wiring(n, side)[2]
    return roles["pose"], roles["echo"]
