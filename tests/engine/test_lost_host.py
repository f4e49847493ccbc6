"""A container host that dies or goes silent is marked lost within 5 s (the keepalive's 4 s and its next 1 s ping), the
owning robot is told (ST and ER), and the host, back, registers cleanly: as a new task set
(the master dropped the old one), destroying the containers the master lost."""
from __future__ import annotations

import asyncio
import os
import signal
import time

import pytest

from rce.transport.rpc import KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio




async def test_silent_host_is_lost_within_5s_and_a_new_host_registers(engine):
    host = next(p for p in engine.procs if "rce-container" in p.args[0])
    async with RawRobot(engine.master_url, "lostBot") as r:
        await r.send("CC", {"containerTag": "lostC"})
        await r.cn(addNodes=[{"containerTag": "lostC", "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}])
        await r.send("DC", {"containerTag": "noSuchC"})          # a marker: once its ER is back, CC is done
        await r.expect("ER", pred=lambda d: "noSuchC" in d)
        before = engine.admin('/api/state')
        assert [c["state"] for c in before["containers"]] == ["running"]
        old_tid = next(t["tid"] for t in before["tasksets"] if t["kind"] == "container")
        os.kill(host.pid, signal.SIGSTOP)                       # silent: socket open, nothing sent
        t0 = time.monotonic()
        try:
            st = await r.expect("ST", timeout=10, pred=lambda d: d.get("topic") == "container")
            lost_after = time.monotonic() - t0
            er = await r.expect("ER", timeout=5, pred=lambda d: "lostC" in d)
            s = engine.admin('/api/state')
        finally:
            os.kill(host.pid, signal.SIGCONT)
        assert st == {"topic": "container", "cTag": "lostC", "status": "lost"}
        assert "host went away" in er
        # the keepalive's timeout, its next ping, and the ST's way to the robot (loaded machines: a second)
        assert lost_after < KEEPALIVE_TIMEOUT + KEEPALIVE_INTERVAL + 1.0, lost_after
        assert [c["state"] for c in s["containers"]] == ["lost"]
        assert not any(t["kind"] == "container" for t in s["tasksets"])
        # the frozen host, woken up, finds its master link gone and registers again: the master
        # dropped its task set, so it is a new one, and the lost container is destroyed there
        log = engine.workdir / "container0.log"
        for _ in range(int(15 / 0.05)):                           # polling the admin API and the log: conditions
            hosts = [t for t in engine.admin("/api/state")["tasksets"] if t["kind"] == "container"]
            if hosts and "the master does not have this container: destroying it" in log.read_text():
                break
            await asyncio.sleep(0.05)
        assert len(hosts) == 1 and hosts[0]["tid"] > old_tid and not hosts[0]["absent"] and host.poll() is None
        assert "the master does not have this container: destroying it" in log.read_text()
        await r.send("CC", {"containerTag": "afterC"})
        await r.send("DC", {"containerTag": "noSuchC2"})
        await r.expect("ER", pred=lambda d: "noSuchC2" in d)
        assert {c["ctag"]: c["state"] for c in engine.admin('/api/state')["containers"]}["afterC"] == "running"


async def test_a_lost_tag_can_be_destroyed_and_created_again_and_a_new_host_takes_the_rest(engine):
    """Containers outlive their host, even with no other host: after kill -9 of the only container
    host, DC of a lost container forgets it at once and CC of its tag is refused with a clear answer
    until then; a lost container not destroyed waits, and is re-created when a host registers."""
    host = next(p for p in engine.procs if "rce-container" in p.args[0])
    async with RawRobot(engine.master_url, "tagBot") as r:
        for ctag in ("goneC", "waitC"):
            await r.send("CC", {"containerTag": ctag})
        await r.cn(setParam=[{"containerTag": "waitC", "name": "p", "value": "kept"}])
        await r.probe()
        os.kill(host.pid, signal.SIGKILL)
        host.wait(10)
        for ctag in ("goneC", "waitC"):
            await r.expect("ST", pred=lambda d, c=ctag: d == {"topic": "container", "cTag": c, "status": "lost"})
        await r.send("CC", {"containerTag": "goneC"})
        er = await r.expect("ER", pred=lambda d: d.startswith("CC:"))
        assert er == ("CC: container 'goneC' was lost with its host and waits for a container host to be re-created "
                      "on; DC it first to create it afresh")
        await r.send("DC", {"containerTag": "goneC"})
        await r.probe()                                   # the DC was answered with no ER
        assert sorted((c["ctag"], c["state"]) for c in engine.admin("/api/containers")) == [("waitC", "lost")]
        await r.send("CC", {"containerTag": "goneC"})     # no host now: refused, naming why
        await r.expect("ER", pred=lambda d: "no container host can take this container" in d)
        engine.add_container_host()
        st = await r.expect("ST", timeout=30, pred=lambda d: d.get("topic") == "container" and d["cTag"] == "waitC")
        assert st["status"] == "running"
        await r.send("CC", {"containerTag": "goneC"})
        await r.expect("ST", pred=lambda d: d.get("topic") == "container" and d["cTag"] == "goneC"
                       and d["status"] == "running")
        s = engine.admin("/api/state")
        assert sorted((c["ctag"], c["state"]) for c in s["containers"]) == [("goneC", "running"), ("waitC", "running")]
        assert [(p["ctag"], p["value"]) for p in s["parameters"]] == [("waitC", "kept")]
