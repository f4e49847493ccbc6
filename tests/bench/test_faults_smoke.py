"""Smoke test of bench/faults.py: ``--quick --no-ros1 --faults master,leader,link`` on real engine
processes, end to end. Whatever the engine survives today, the run ends, and its JSON has every fault
run (rce, and the ROS 1 rows marked skipped) with every field, figures that agree with each other, the
commands it ran, and the PNG. The three faults run here are the ones whose harness is the bench's own
(a master restarted, etcd's leader, the proxy that cuts the link); the other three (a robot endpoint, a
host, an environment killed with -9) are the engine's own tests (test_endpoint_failover, test_lost_host,
test_failover), and each fault costs the smoke about 10 s."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RCE_FAULTS = ("master", "leader", "link")
ROS1_FAULTS = ("master", "link")
FIELDS = ("fault", "system", "description", "survived", "served_again_s", "lost", "lost_seqs", "measured",
          "echoed", "not_sent", "duplicates", "max_gap_s", "notes", "extra", "events", "commands", "timeline")
RUN_TIMEOUT = 240        # s: three faults, each on a fresh engine, at most a 10 s wait after each fault (--quick)


@pytest.mark.timeout(RUN_TIMEOUT + 30)
def test_faults_smoke(tmp_path):
    out, png = tmp_path / "faults.json", tmp_path / "faults.png"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "faults.py"), "--quick", "--no-ros1",
                        "--faults", ",".join(RCE_FAULTS), "--json", str(out), "--plot", str(png)],
                       cwd=ROOT, capture_output=True, text=True, timeout=RUN_TIMEOUT,
                       env=dict(os.environ, COLUMNS="160"))
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    assert "served again after (s)" in r.stdout                      # the table was printed
    d = json.loads(out.read_text())
    assert d["quick"] is True and d["rate_hz"] == 10 and d["commit"] and d["date"] and "faults.py" in d["command"]
    bound = d["timing"]["bound"]
    rows = {(x["fault"], x["system"]): x for x in d["results"]}
    assert set(rows) == {(f, "rce") for f in RCE_FAULTS} | {(f, "ros1") for f in ROS1_FAULTS}
    assert set(d["machine_load"]) == {f"{f}/{s}" for f, s in rows}
    for (fault, system), x in rows.items():
        assert set(FIELDS) <= set(x), (fault, system, set(FIELDS) - set(x))
        assert x["description"] and x["notes"], x
        if system == "ros1":
            assert "skipped" in x["notes"] and x["survived"] is None, x
            continue
        assert "error" not in x, (fault, x.get("error"))
        assert x["measured"] > 0 and 0 <= x["lost"] <= x["measured"] and x["echoed"] == x["measured"] - x["lost"], x
        assert len(x["timeline"]) == x["measured"]
        assert sum(1 for _, rtt in x["timeline"] if rtt is None) == x["lost"]
        assert 0 <= x["not_sent"] <= x["lost"] and x["duplicates"] >= 0
        assert isinstance(x["survived"], bool) and (x["served_again_s"] is not None) == x["survived"], x
        if x["survived"]:
            assert 0 < x["served_again_s"] <= bound, x
        assert [e for e in x["events"] if e[0] == 0 and e[1].startswith("fault: ")], x["events"]
        assert any("rce-master" in c for c in x["commands"]) and any("rce-robot" in c for c in x["commands"])
        assert x["extra"]["client"].startswith("rce_client.Connection")
    assert rows[("link", "rce")]["extra"]["proxy"]["reset"] >= 1               # the cut reset the robot's link
    for fault in ("master", "leader"):
        assert "new_request_s" in rows[(fault, "rce")]["extra"] and "login_s" in rows[(fault, "rce")]["extra"]
    assert "leader_s" in rows[("leader", "rce")]["extra"]
    assert any("etcd" in c for c in rows[("leader", "rce")]["commands"])
    assert png.stat().st_size > 10_000
