"""``rce-fleet demo --mission --edge-hosts --out-of-coverage Robot2``: every robot gets a computer of
its own (a container host in zone ``robot:RobotN``) and its move_client a container of its own,
wired to the planner through container-to-container connections. The placer places the covered
robots' move_clients (``auto``); Robot2, out of coverage, keeps its move_client on board. The mission
is driven through the split containers: every robot reaches its goal.

On the lab map (1 m cells), Robot2 (38 -> 55) and Robot1 (60 -> 62) stay within 4 m of each other
the whole way, so Robot2 always hears a relay within the 6 m radio range (the drives out of range
and back are tests/fleet/test_fleet_coverage.py's)."""
from __future__ import annotations

from rce_fleet.configs import robot_config

from .test_fleet_e2e import _explain, run_demo


def test_move_clients_in_containers_of_their_own_placed_by_the_placer(tmp_path):
    mission = ("--start", "Robot2=38", "--goal", "Robot2=55", "--start", "Robot1=60", "--goal", "Robot1=62")
    code, rep, out = run_demo(tmp_path, "--edge-hosts", "--out-of-coverage", "Robot2", "--radio-range", "6", *mission)
    assert code == 0 and rep["ok"], _explain(rep, out)
    placed = {c["ctag"]: c for c in rep["placement"]["containers"]}
    assert set(placed) == {"mc_Robot1", "mc_Robot2", "mc_Robot3"}
    assert placed["mc_Robot2"]["runs"].startswith("robot:Robot2"), placed["mc_Robot2"]
    for c in placed.values():
        assert c["results"] > 0 and c["misses"] == 0, c          # poses in, goals out, timed by the engine
        assert c["runs"].split(" ")[0] in ("cloud", f"robot:{c['ctag'][3:]}"), c
    assert "move_clients ran on:" in out


def test_a_split_config_wires_the_move_client_to_the_planner_and_the_robot():
    cfg = robot_config(4, placement="auto", params={"/fleet/grid": {"w": 1}})
    assert cfg["containers"] == [{"cTag": "mc_Robot4", "placement": "auto", "robot": "Robot4", "deadline_ms": 200,
                                  "consumes": ["amclPoseSender_4"]}]
    assert cfg["nodes"][0]["cTag"] == "mc_Robot4" and cfg["parameters"][0]["cTag"] == "mc_Robot4"
    links = {(c["tagA"], c["tagB"]) for c in cfg["connections"]}
    assert ("cTag_01/goalNodesListOut_4", "mc_Robot4/goalNodesListIn_4") in links
    assert ("mc_Robot4/progressOut_4", "cTag_01/progressIn_4") in links
    assert ("mc_Robot4/goalSender_4", "Robot4/goalReceiver_4") in links
    poses = {a for a, b in links if b == "Robot4/amclPoseSender_4"}
    assert poses == {"cTag_01/amclPoseReceiver_4", "mc_Robot4/amclPoseReceiver_4"}, "the pose goes to both"
    assert robot_config(4)["containers"] == [] and robot_config(4)["nodes"][0]["cTag"] == "cTag_01"
