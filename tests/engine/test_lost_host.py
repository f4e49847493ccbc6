"""Issue 3, part 7: a container host that dies or goes silent is marked lost within 5 s, the
owning robot is told (ST and ER), and a restarted host registers cleanly."""
from __future__ import annotations

import os
import signal
import time

import pytest

from wsclient import RawRobot

pytestmark = pytest.mark.asyncio




async def test_silent_host_is_lost_within_5s_and_a_new_host_registers(engine):
    host = next(p for p in engine.procs if "rce-container" in p.args[0])
    async with RawRobot(engine.master_url, "lostBot") as r:
        await r.send("CC", {"containerTag": "lostC"})
        await r.cn(addNodes=[{"containerTag": "lostC", "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}])
        await r.send("DC", {"containerTag": "noSuchC"})          # a marker: once its ER is back, CC is done
        await r.expect("ER", pred=lambda d: "noSuchC" in d)
        assert [c["state"] for c in engine.admin('/api/state')["containers"]] == ["running"]
        os.kill(host.pid, signal.SIGSTOP)                       # silent: socket open, nothing sent
        t0 = time.monotonic()
        try:
            st = await r.expect("ST", timeout=10, pred=lambda d: d.get("topic") == "container")
            lost_after = time.monotonic() - t0
            er = await r.expect("ER", timeout=5, pred=lambda d: "lostC" in d)
        finally:
            os.kill(host.pid, signal.SIGCONT)
        assert st == {"topic": "container", "cTag": "lostC", "status": "lost"}
        assert "host went away" in er
        assert lost_after < 5.0
        s = engine.admin('/api/state')
        assert [c["state"] for c in s["containers"]] == ["lost"]
        assert not any(t["kind"] == "container" for t in s["tasksets"])
        # the frozen host, woken up, finds its master link gone and stops with its containers
        host.wait(15)
        # a restarted host registers cleanly and serves new containers
        engine.add_container_host()
        assert sum(t["kind"] == "container" for t in engine.admin('/api/state')["tasksets"]) == 1
        await r.send("CC", {"containerTag": "afterC"})
        await r.send("DC", {"containerTag": "noSuchC2"})
        await r.expect("ER", pred=lambda d: "noSuchC2" in d)
        assert {c["ctag"]: c["state"] for c in engine.admin('/api/state')["containers"]}["afterC"] == "running"
