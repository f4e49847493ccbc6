"""Containers through the real engine (master, robot task set, namespaced container host) and
rce-console: the sandbox a robot is told about, node exits and respawns as ST/ER, kept logs,
an OOM kill with its reason, usage in the admin API and `rce-console top`, live resizing from
the console and from CN, and teardown on robot disconnect (no process, no cgroup left)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from container.harness import make_helper_package
from rce.tools.launch import start_engine
from wsclient import RawRobot

pytestmark = [pytest.mark.asyncio, pytest.mark.timeout(120)]

BIN = Path(sys.executable).parent


@pytest.fixture
def sb_engine(tmp_path):
    assert os.geteuid() == 0, "the namespaced sandbox needs root; CI runs the test suite as root"
    pkgs = make_helper_package(tmp_path / "pkgs")
    e = start_engine(tmp_path / "engine", env={"RCE_PACKAGE_PATH": str(pkgs)},
                     container_args=("--sandbox", "namespaced", "--grace", "1"))
    yield e
    e.stop()


def console(eng, *args) -> str:
    p = subprocess.run([str(BIN / "rce-console"), "--master", eng.master_url, *args], capture_output=True,
                       text=True, env=eng.env, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout




def node_st(ctag: str, ntag: str, status: str):
    return lambda d: d.get("topic") == "node" and d.get("cTag") == ctag and d.get("nTag") == ntag \
        and d.get("status") == status


async def test_containers_end_to_end_through_master_and_console(sb_engine):
    eng = sb_engine
    async with RawRobot(eng.master_url, "sbBot") as r:
        # size 1: what the original RCE's client always sends (a size class, not a limit)
        await r.send("CC", {"containerTag": "sbC", "containerData": {"cpu": 0.5, "memory": 256, "pids": 64, "size": 1}})
        st = await r.expect("ST", pred=lambda d: d.get("topic") == "container")
        assert st == {"topic": "container", "cTag": "sbC", "status": "running", "sandbox": "namespaced"}
        await r.cn(addNodes=[
            {"containerTag": "sbC", "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"},
            {"containerTag": "sbC", "nodeTag": "crash", "pkg": "CTest", "exe": "exiter.py", "args": "3",
             "respawn": {"delay": 0.1, "limit": 1}}])
        # exit reported, respawned once, then given up on: ST for each step, ER for the non-zero exits
        resp = await r.expect("ST", pred=node_st("sbC", "crash", "respawning"))
        assert resp["code"] == 3
        final = await r.expect("ST", pred=node_st("sbC", "crash", "exited"))
        assert final["code"] == 3 and final["reason"] == "respawn limit reached"
        er = await r.expect("ER", pred=lambda d: "'crash'" in d and "respawn limit" in d)
        assert "code 3" in er
        # kept output, through rce-console
        logs = console(eng, "logs", "testUser", "sbC", "crash").splitlines()
        assert logs == ["stdout: argv=3", "stdout: argv=3", "stderr: bye", "stderr: bye"]

        # a node killed by the kernel for memory: ST and ER say so
        await r.send("CC", {"containerTag": "oomC", "containerData": {"memory": 48}})
        await r.cn(addNodes=[{"containerTag": "oomC", "nodeTag": "hog", "pkg": "CTest", "exe": "hog.py"}])
        oom = await r.expect("ST", timeout=30, pred=node_st("oomC", "hog", "exited"))
        assert oom["signal"] == 9 and oom["reason"] == "killed: out of memory (limit 48 MiB)"
        assert "out of memory" in await r.expect("ER", pred=lambda d: "'hog'" in d)

        containers = {c["ctag"]: c for c in json.loads(console(eng, "--json", "containers"))}
        assert containers["sbC"]["sandbox"] == containers["oomC"]["sandbox"] == "namespaced"

        # usage: admin API and rce-console top (container row, then one row per node)
        deadline = time.monotonic() + 20
        while not (s := eng.admin("/api/containers/testUser/sbC/stats"))["per_node"]["echo"]["connected"]:
            assert time.monotonic() < deadline, s
            time.sleep(0.1)
        assert s["sandbox"] == "namespaced" and s["processes"] >= 3 and s["rss_mib"] > 5
        assert s["per_node"]["echo"]["running"] and s["per_node"]["echo"]["rss_mib"] > 5
        assert s["per_node"]["crash"]["running"] is False and s["per_node"]["crash"]["last_exit"] == {"code": 3}
        rows = json.loads(console(eng, "--json", "top", "--once"))
        crow = next(x for x in rows if x.get("container") == "testUser/sbC")
        assert crow["state"] == "namespaced" and crow["processes"] >= 3 and crow["rss_mib"] > 5
        assert "cpu=0.5" in crow["limits"] and "memory=256" in crow["limits"]
        nrows = {x["node"]: x for x in rows if x.get("node")}
        assert nrows["echo"]["state"] == "running" and nrows["echo"]["rss_mib"] > 5
        assert nrows["crash"]["state"] == "exited code 3"
        assert nrows["hog"]["state"] == "exited signal 9"
        table = console(eng, "top", "--once")
        assert "testUser/sbC" in table and "cpu_percent" in table and "echo" in table

        # resize while running: from the console, and from the robot (CN resizeContainer)
        echo_pid = s["per_node"]["echo"]["pid"]
        out = console(eng, "container", "resize", "testUser", "sbC", "--cpu", "1.5", "--memory", "300", "--pids", "80")
        assert "resized" in out
        await r.cn(resizeContainer=[{"containerTag": "sbC", "size": 2}])      # a size class: recorded only
        deadline = time.monotonic() + 20
        while (s := eng.admin("/api/containers/testUser/sbC/stats"))["limits"].get("size") != 2:
            assert time.monotonic() < deadline, s["limits"]
            time.sleep(0.05)
        files = s["sandbox_info"]["cgroup"]["files"]
        assert files["pids.max"] == "80"
        assert files.get("cpu.cfs_quota_us", files.get("cpu.max", "").split(" ")[0]) == "150000"
        assert files.get("memory.limit_in_bytes", files.get("memory.max")) == str(300 << 20)
        assert s["limits"] == {"cpu": 1.5, "memory": 300, "pids": 80, "size": 2}
        assert s["per_node"]["echo"]["pid"] == echo_pid and psutil.Process(echo_pid).is_running()
        assert eng.admin("/api/containers/testUser/sbC/call",
                   {"service": "/stringEchoService", "request": {"data": "resized"}}) == {"data": "resized"}
        assert {c["ctag"]: c for c in json.loads(console(eng, "--json", "containers"))}["sbC"]["data"]["memory"] == 300

        # what must be gone after the robot leaves
        footprint = []
        for ctag in ("sbC", "oomC"):
            info = eng.admin(f"/api/containers/testUser/{ctag}/stats")["sandbox_info"]
            dirs = [Path(d) for d in info["cgroup"]["dirs"]]
            footprint.append((dirs, [int(p) for p in (dirs[0] / "cgroup.procs").read_text().split()]))
        assert footprint[0][1]
    # robot disconnect: the master destroys its containers; the host kills and removes everything
    deadline = time.monotonic() + 20
    while eng.admin("/api/containers"):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    for dirs, pids in footprint:
        while any(d.exists() for d in dirs) or [p for p in pids if running(p)]:
            assert time.monotonic() < deadline, (dirs, [p for p in pids if running(p)])
            time.sleep(0.05)


def running(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False
