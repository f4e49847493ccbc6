"""Smoke test of bench/fleet_load.py: 5 robots for 2 s against the real engine (fleet container
with the global planner and the pose echo), against the transport floor (bench/fleet_floor.py,
real processes on loopback) and against the relay floor (the same with a relay and an echo
process), JSON of the documented shape, positive latencies and nothing lost at that tiny load,
and the PNG."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def finite_pos(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.mark.timeout(100)
def test_fleet_load_smoke(tmp_path):
    out, png = tmp_path / "fleet_load.json", tmp_path / "fleet_load.png"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "fleet_load.py"), "--robots", "5", "--duration", "2",
                        "--relay-floor", "--json", str(out), "--plot", str(png)], cwd=ROOT, capture_output=True,
                       text=True, timeout=95, env=dict(os.environ, COLUMNS="160"))
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    d = json.loads(out.read_text())
    assert d["robots"] == [5] and d["mode"] == "forwarder" and d["rate_hz"] == 10
    assert {"latency", "lost", "cpu_pct", "peak_rss_mib", "bytes_per_robot_s"} <= set(d["definitions"])
    assert "stop_reason" in d and "stopped_at" in d
    (run,) = d["runs"]
    assert "error" not in run, run.get("error")
    assert run["robots"] == 5
    lat = run["latency_ms"]
    assert all(finite_pos(lat[k]) for k in ("p50", "p90", "p99", "max")), lat
    assert lat["p50"] <= lat["p99"] <= lat["max"]
    # 5 robots x 2 s x 10 Hz, every pose echoed exactly once
    assert run["sent"] >= 60, run["sent"]
    assert run["lost"] == 0 and run["received"] == run["sent"] == lat["samples"], run
    assert run["duplicates"] == 0 and not run["robots_losing"]
    assert all(v == 0 for v in run["engine_drops"].values()), run["engine_drops"]
    assert finite_pos(run["planner_view_age_ms"]["p50"])
    assert run["goal_to_path_ms"]["robots_with_path"] == 5
    b = run["bytes_per_robot_s"]
    assert finite_pos(b["up"]) and finite_pos(b["down"]) and b["total"] == pytest.approx(b["up"] + b["down"])
    # a forwarder pose is one JSON frame + one binary part of > 300 bytes, 10 times a second
    assert b["up"] > 10 * 300
    for k in ("master", "robot", "container (all)", "clients", "machine"):
        assert k in run["cpu_pct"], (k, run["cpu_pct"])
    assert run["cpu_pct"]["robot"] > 0 and run["cpu_pct"]["clients"] > 0
    for k in ("master", "robot", "container host", "environment", "planner", "echo node", "clients"):
        assert finite_pos(run["peak_rss_mib"].get(k)), (k, run["peak_rss_mib"])
    s = run["setup"]
    for k in ("engine_s", "fleet_container_s", "robots_s", "warmup_s", "goals_s", "total_s"):
        assert finite_pos(s[k]), (k, s)
    assert s["robots_failed"] == 0
    # the transport floor: the same robots and window, every pose echoed straight back, by floor processes
    floor = run["floor"]
    assert "error" not in floor, floor.get("error")
    assert "floor" in d["definitions"] and floor["robots"] == 5
    flat = floor["latency_ms"]
    assert all(finite_pos(flat[k]) for k in ("p50", "p99")) and flat["p50"] <= flat["p99"]
    assert floor["sent"] >= 60 and floor["lost"] == 0 and floor["received"] == floor["sent"] == flat["samples"]
    assert floor["cpu_pct"]["floor"] > 0 and floor["cpu_pct"]["clients"] > 0
    assert floor["bytes_per_robot_s"]["up"] > 10 * 300
    # the engine's CPU per pose over the floor's, both measured here
    assert "engine_over_floor" in d["definitions"] and finite_pos(run["engine_over_floor"])
    us = run["cpu_us_per_pose"]
    assert run["engine_over_floor"] == pytest.approx(
        (us["master"] + us["robot"] + us["container (all)"]) / floor["cpu_us_per_pose"]["floor"], rel=0.02)
    # the relay floor: the same, each pose through a relay process and an echo process and back
    relay = run["relay_floor"]
    assert "error" not in relay, relay.get("error")
    assert relay["sent"] >= 60 and relay["lost"] == 0 and relay["received"] == relay["sent"]
    assert len([p for p in relay["cpu_by_process"] if p["label"] == "floor"]) >= 2     # the relays and the echo
    assert finite_pos(run["engine_over_relay_floor"]) and finite_pos(run["relay_floor_over_floor"])
    assert run["engine_over_relay_floor"] == pytest.approx(
        (us["master"] + us["robot"] + us["container (all)"]) / relay["cpu_us_per_pose"]["floor"], rel=0.02)
    assert png.stat().st_size > 10_000
