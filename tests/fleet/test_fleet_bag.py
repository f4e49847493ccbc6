"""The seed paper's blocked cell on turtlebot3_world (test_fleet_e2e's mission with cell 26
blocked at 5 s), run once with ``--bag``: the robots whose paths crossed the cell re-route around
it (the report's simulator ground truth), and the fleet topics of the run are in a ROS 1 bag,
read back with the rosbags reader and Debian's ``rosbag info``."""
from __future__ import annotations

import shutil
import subprocess

import pytest
import yaml
from rosbags.rosbag1 import Reader

from rce.messages import MessageRegistry
from rce.node.package_path import load_package_types

from .test_fleet_e2e import RADIUS, TB3, TB3_MISSION, _explain, run_demo

ROSBAG_HINT = "Debian's rosbag is missing: apt-get install -y python3-rosbag (.ci/system-deps installs it as root)"
ROSBAG_INFO_TIMEOUT_S = 60.0   # wall s for `rosbag info` to read the bag


@pytest.fixture(scope="module")
def blocked(tmp_path_factory):
    """The mission with cell 26 blocked at 5 s, recorded: (exit code, report, output, bag path)."""
    d = tmp_path_factory.mktemp("blocked")
    bag = d / "fleet.bag"
    code, rep, out = run_demo(d, "--map", str(TB3), "--grid", "8x8", "--speedup", "4", *TB3_MISSION,
                              "--block", "26@5", "--bag", str(bag))
    return code, rep, out, bag


def test_blocking_cell_26_reroutes_exactly_the_robots_that_crossed_it(blocked):
    code, rep, out, _ = blocked
    assert code == 0 and rep["ok"], _explain(rep, out)
    (blk,) = rep["blocks"]
    assert blk["cell"] == 26 and blk["sent_sim_s"] == pytest.approx(5.0, abs=0.15)
    crossed = set(blk["paths_crossed"])
    assert crossed == {"Robot1", "Robot2"}, blk
    cancelled = {r for r, v in rep["per_robot"].items() if v["cancel_goal"] > 0}
    assert cancelled == crossed
    assert all(rep["per_robot"][r]["cancel_goal"] == 1 for r in crossed)
    # nobody's centre entered cell 26 after the block (simulator ground truth)
    assert blk["entered_after"] == []
    for r, v in rep["per_robot"].items():
        assert 26 not in [c for t, c in v["cells"] if t >= 5.0], (r, v["cells"])
        assert v["reached"]
    # the re-routed robots went around through 35-34-33
    for r in crossed:
        assert 34 in [c for _, c in rep["per_robot"][r]["cells"]]
    assert rep["blocked"] == {"26": "operator"}
    assert rep["min_pair_distance_m"] > 2 * RADIUS


def test_demo_records_the_fleet_topics(blocked):
    code, rep, out, bag = blocked
    # the blocking of cell 26 at 5 s sends cancelGoal to Robot1 and Robot2
    assert code == 0 and rep["ok"], _explain(rep, out)
    assert bag.exists() and not bag.with_name("fleet.bag.active").exists()

    reg = MessageRegistry()
    load_package_types(reg)          # fleet/FleetState comes from the fleet package
    counts: dict[str, int] = {}
    last: dict[str, object] = {}
    with Reader(bag) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        stamps = []
        for c, t, raw in r.messages():
            counts[c.topic] = counts.get(c.topic, 0) + 1
            last[c.topic] = reg.deserialize(c.msgtype, raw)
            stamps.append(t)
    assert counts == rep["bag"]["messages"] and rep["bag"]["path"].endswith("fleet.bag")
    robots = ("Robot1", "Robot2", "Robot3")
    for r in robots:
        assert types[f"/{r}/amcl_pose"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
        assert types[f"/{r}/goalNodesList"] == "std_msgs/msg/Int32MultiArray"
        assert counts[f"/{r}/amcl_pose"] > 20 and counts[f"/{r}/goalNodesList"] >= 1
        assert last[f"/{r}/amcl_pose"].header.frame_id == "map"
        assert int(last[f"/{r}/goalNodesList"].data[-1]) == rep["per_robot"][r]["goal"]   # the path ends at the goal
    for r in ("Robot1", "Robot2"):       # exactly the robots whose paths crossed cell 26
        assert types[f"/{r}/cancelGoal"] == "std_msgs/msg/Bool" and last[f"/{r}/cancelGoal"].data is True
    assert "/Robot3/cancelGoal" not in counts
    assert types["/fleet/state"] == "fleet/msg/FleetState" and counts["/fleet/state"] > 5
    assert sorted(x.robot for x in last["/fleet/state"].robots) == list(robots)
    assert stamps == sorted(stamps)

    exe = shutil.which("rosbag")
    if exe is None:
        pytest.fail(ROSBAG_HINT)
    p = subprocess.run([exe, "info", "--yaml", str(bag)], capture_output=True, text=True,
                       timeout=ROSBAG_INFO_TIMEOUT_S)
    assert p.returncode == 0, p.stderr
    info = yaml.safe_load(p.stdout)
    assert info["messages"] == sum(counts.values())
    assert {t["topic"]: t["messages"] for t in info["topics"]} == counts
    assert {t["topic"]: t["type"] for t in info["topics"]}["/fleet/state"] == "fleet/FleetState"
