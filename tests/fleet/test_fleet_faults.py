"""The fleet survives faults: ``rce-fleet demo --fault`` as a subprocess on the small
default map with 3 robots, and the mission still ends with every robot at its goal (exit 0).

* ``--fault master@3``: rce-master is killed (kill -9) 3 sim s into the mission and started again
  on its ``--state`` file and ports 2 s later. The robots' data never stops (the fleet state keeps
  coming), the task sets re-register, and login answers again.
* ``--fault link:Robot1@3+5``: Robot1's websocket is cut for 5 s at the demo's proxy. Its bridge
  resumes the session, with no message lost.

Each asserts on the report (``--report``): the fault, when it happened and when the fleet was
served again (docs of the fields: ``rce_fleet.live.faults``).
"""
from __future__ import annotations

import json
import subprocess

from rce.transport.masterlink import BACKOFF_CAP
from rce_client.connection import RECONNECT_WAIT_MAX

from .test_fleet_e2e import RCE_FLEET, _explain, run_demo

SPEEDUP = "4"           # sim s per wall s: the mission takes ~25 s sim, under 10 s wall
FAULT_AT = 3.0          # sim s after the goals: the robots are on their way (the last arrives after ~25 s)
MASTER_DOWN = 2.0       # wall s the master stays dead (the default of master@T)
LINK_CUT = 5.0          # wall s Robot1's link is cut
SERVED_AGAIN_BOUND = BACKOFF_CAP + 3.0   # s from the restarted master's ready file to every task set registered and
                                         # login 200: one backoff delay at most, then a dial and a register (which
                                         # take seconds on a 2-core machine running the suite in parallel)
RESUME_BOUND = RECONNECT_WAIT_MAX + 1.0  # s from the link's return to the session resumed: one backoff step of the
                                         # client, then a handshake on loopback
STATE_GAP_BOUND = MASTER_DOWN   # s the fleet state (5 Hz) may pause during a fault: a stop would last the whole
                                # fault (2 s for the master, 5 s for the link); a busy machine pauses it ~1 s


def _fault(rep: dict, out: str) -> dict:
    """The report's one fault, injected mid-mission and recovered from."""
    assert rep["ok"] and all(v["reached"] for v in rep["per_robot"].values()), _explain(rep, out)
    (fault,) = rep["faults"]
    print(json.dumps(fault))
    assert fault["injected"] and fault["recovered"], fault
    assert abs(fault["injected_sim_s"] - FAULT_AT) < 0.5, fault
    assert fault["injected_sim_s"] < rep["mission_time_s"], (fault, rep["mission_time_s"])
    assert fault["fleet_state_max_gap_s"] < STATE_GAP_BOUND, fault
    return fault


def test_master_killed_and_restarted_mid_mission(tmp_path):
    code, rep, out = run_demo(tmp_path, "--speedup", SPEEDUP, "--fault", f"master@{FAULT_AT:g}")
    assert code == 0, _explain(rep, out)
    fault = _fault(rep, out)
    assert fault["fault"] == "master" and fault["duration_s"] == MASTER_DOWN
    assert 0 < fault["served_again_after_s"] < SERVED_AGAIN_BOUND, fault
    assert MASTER_DOWN < fault["recovered_after_s"] < MASTER_DOWN + fault["restart_s"] + SERVED_AGAIN_BOUND, fault
    engine = tmp_path / "run" / "engine"
    assert (engine / "master.sqlite3").exists() and (engine / "master1.log").exists()   # the restarted master


def test_robot_link_cut_for_5_s_mid_mission(tmp_path):
    code, rep, out = run_demo(tmp_path, "--speedup", SPEEDUP, "--fault", f"link:Robot1@{FAULT_AT:g}+{LINK_CUT:g}")
    assert code == 0, _explain(rep, out)
    fault = _fault(rep, out)
    assert fault["fault"] == "link:Robot1" and fault["duration_s"] == LINK_CUT
    assert fault["dropped"] == 0, fault
    assert 0 < fault["served_again_after_s"] < RESUME_BOUND, fault
    assert LINK_CUT < fault["recovered_after_s"] < LINK_CUT + RESUME_BOUND, fault
    assert "link to the cloud lost" in out and "Robot1" in out


def test_bad_fault_flags_are_refused(tmp_path):
    for flag, says in (("master", "expected master@T"), ("link:Robot1@-1", "T must be >= 0"),
                       ("reboot@3", "unknown fault 'reboot'"), ("link:Robot9@3", "unknown robot 'Robot9'")):
        p = subprocess.run([str(RCE_FLEET), "demo", "--mission", "--fault", flag], capture_output=True, text=True,
                           cwd=tmp_path)
        assert p.returncode == 2 and says in p.stderr, (flag, p.stderr)
