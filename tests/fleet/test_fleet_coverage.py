"""Robots out of coverage: ``rce-fleet demo --out-of-coverage Robot2 --radio-range 4`` as a subprocess
on the lab map with 3 robots. Robot2 has no path of its own; Robot1 and Robot3 relay for it
(rce_client.relay) over simulated radio links that are up only while the robots are within 4 m.

Robot2 (31 -> 63) starts 1 m from Robot1 and 2.2 m from Robot3. Robot1 drives to the far corner
(30 -> 0) and out of range; Robot3 (46 -> 61) stays near Robot2's way. So Robot2 logs in through
Robot1, loses it as Robot1 drives away, resumes its session through Robot3, and reaches its goal.
"""
from __future__ import annotations

import json
import subprocess

from .test_fleet_e2e import RCE_FLEET, _explain, run_demo

MISSION = ["--start", "Robot1=30", "--goal", "Robot1=0", "--start", "Robot2=31", "--goal", "Robot2=63",
           "--start", "Robot3=46", "--goal", "Robot3=61"]


def test_a_robot_out_of_coverage_reaches_its_goal_through_relays(tmp_path):
    code, rep, out = run_demo(tmp_path, "--speedup", "4", "--out-of-coverage", "Robot2", "--radio-range", "4",
                              *MISSION)
    assert code == 0 and rep["ok"], _explain(rep, out)
    assert all(v["reached"] for v in rep["per_robot"].values())
    cov = rep["coverage"]
    print(json.dumps(cov["followers"]))
    assert cov["radio_range_m"] == 4 and cov["out_of_coverage"] == ["Robot2"]
    assert cov["relays"] == ["Robot1", "Robot3"]
    f = cov["followers"]["Robot2"]
    # through Robot1 first; Robot1 drove out of range (its radio link went down), then through Robot3
    assert set(f["relays_used"]) == {"Robot1", "Robot3"} and f["via_now"] == "Robot3", f
    assert cov["links"]["Robot2-Robot1"]["went_out"] >= 1 and cov["links"]["Robot2-Robot1"]["reset"] >= 1
    assert f["switches"] >= 1 and f["dark"] and f["dark_now_s"] == 0.0, f
    assert all(d["dropped"] == 0 for d in f["dark"]) and f["lost_to_cloud"] == 0, f
    # the master saw the topology: Robot2's link goes through Robot3 at the end
    assert cov["master"]["Robot2"]["relay"] == "Robot3" and cov["master"]["Robot2"]["relay_since"] > 0
    # Robot2's traffic crossed both radio links, both ways
    assert all(cov["links"][k]["bytes_up"] > 0 and cov["links"][k]["bytes_down"] > 0
               for k in ("Robot2-Robot1", "Robot2-Robot3")), cov["links"]


def test_bad_coverage_flags_are_refused(tmp_path):
    for flags, says in ((["--out-of-coverage", "Robot9"], "unknown robot 'Robot9'"),
                        (["--robots", "2", "--out-of-coverage", "Robot1,Robot2"], "at least one robot must have"),
                        (["--out-of-coverage", "Robot2", "--fault", "link:Robot2@3"], "Robot2 is out of coverage")):
        p = subprocess.run([str(RCE_FLEET), "demo", "--mission", *flags], capture_output=True, text=True, cwd=tmp_path)
        assert p.returncode == 2 and says in p.stderr, (flags, p.stderr)
