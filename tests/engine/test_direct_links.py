"""Direct links: a node's topic traffic goes straight between the node and the robot
endpoint, past its environment (rce_container/direct_routes.py, rce/node/links.py), and back
through the environment whenever the bus has other subscribers or a link dies.

Real processes on loopback (namespaced sandbox when root), the raw wire protocol."""
from __future__ import annotations

import asyncio
import os
import signal
import time
from pathlib import Path

import pytest

from test_dataflow import _echo_container
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
WAIT = 30.0      # s, the most a step that normally takes well under a second may take


PACKAGES = Path(__file__).resolve().parents[2] / "bench" / "packages"     # benchecho: a topic echo node


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    """The module's engine, with bench/packages on its package path (its tests use distinct robots and containers)."""
    from rce.tools.launch import start_engine
    e = start_engine(tmp_path_factory.mktemp("engine"), env={"RCE_PACKAGE_PATH": str(PACKAGES)})
    yield e
    e.stop()


def stats(eng, ctag: str) -> dict:
    return eng.admin(f"/api/containers/testUser/{ctag}/stats")


async def until(what, pred, timeout: float = WAIT):
    """Poll ``what()`` (off the loop) until ``pred(value)``; the last value on timeout fails."""
    deadline = time.monotonic() + timeout
    while True:
        v = await asyncio.to_thread(what)
        if pred(v):
            return v
        assert time.monotonic() < deadline, v
        await asyncio.sleep(0.05)


async def echo(r: RawRobot, text: str, timeout: float = 0.5) -> dict | None:
    await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": text}})
    try:
        return await r.expect("DM", timeout=timeout, pred=lambda d: d["iTag"] == "resp" and d["msg"]["data"] == text)
    except TimeoutError:
        return None


async def first_echo(r: RawRobot, prefix: str) -> None:
    deadline = time.monotonic() + WAIT
    i = 0
    while await echo(r, f"{prefix}{i}") is None:
        assert time.monotonic() < deadline, "no echo"
        i += 1


async def topic_echo(r: RawRobot, ctag: str, nodes: list[dict], req: str, resp: str) -> None:
    """Container ``ctag`` with ``nodes`` (addNodes entries), a PublisherInterface ``req`` and a
    SubscriberInterface ``resp`` wired to the robot's converters ``req`` and ``resp``."""
    rid = r.robot
    await r.send("CC", {"containerTag": ctag})
    await r.cn(addNodes=[{"containerTag": ctag, **n} for n in nodes],
               addInterfaces=[{"endpointTag": ep, "interfaceTag": tag, "interfaceType": kind,
                               "className": "std_msgs/String", **({"addr": addr} if addr else {})}
                              for ep, tag, kind, addr in ((ctag, "req", "PublisherInterface", req),
                                                          (ctag, "resp", "SubscriberInterface", resp),
                                                          (rid, "req", "SubscriberConverter", None),
                                                          (rid, "resp", "PublisherConverter", None))])
    await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in ("req", "resp")]})
    await r.wait_up("req", "resp")


def direct(s: dict) -> dict:
    return s["environment"]["direct"]


async def test_converter_echo_goes_past_the_environment(eng):
    async with RawRobot(eng.master_url, "directR") as r:
        await _echo_container(r, "directC", "Converter")
        await first_echo(r, "warm")
        # the node claims 'req' (it is /stringEchoReq's only subscriber) and routes /stringEchoResp
        s = await until(lambda: stats(eng, "directC"), lambda s: direct(s)["claims"] >= 1 and direct(s)["routes"] >= 1)
        assert direct(s)["links"] >= 1 and direct(s)["enabled"] is True
        before = s["environment"]["dataplane"]
        ifs = {i["tag"].rsplit("/", 1)[-1]: i for i in s["interfaces"]}
        n = 50
        for i in range(n):
            assert await echo(r, f"m{i}", timeout=5.0) is not None
        s = stats(eng, "directC")
        after = s["environment"]["dataplane"]
        # not one of the 2 x 50 messages crossed the environment's data plane ...
        assert after["msgs_in"] - before["msgs_in"] < 5 and after["msgs_out"] - before["msgs_out"] < 5
        # ... yet the interfaces' counters (reported by the node) show them
        now = {i["tag"].rsplit("/", 1)[-1]: i for i in s["interfaces"]}
        assert now["req"]["msgs_in"] - ifs["req"]["msgs_in"] >= n
        assert now["resp"]["msgs_out"] - ifs["resp"]["msgs_out"] >= n
        assert now["resp"]["bytes_out"] > ifs["resp"]["bytes_out"]
        # a service call still goes through the bus
        await r.send("DM", {"iTag": "srv", "type": "Test/StringEcho", "msgID": "c1", "msg": {"data": "svc"}})
        dm = await r.expect("DM", pred=lambda d: d["iTag"] == "srv")
        assert dm["msg"] == {"data": "svc"}


async def test_another_subscriber_ends_the_claim_and_sees_every_message(eng):
    """A bus_sample on /stringEchoReq is a second subscriber: the claim ends, the sample gets the
    robot's messages, and the node still echoes them; afterwards the claim comes back."""
    async with RawRobot(eng.master_url, "directS") as r:
        await _echo_container(r, "directSC", "Converter")
        await first_echo(r, "warm")
        await until(lambda: stats(eng, "directSC"), lambda s: direct(s)["claims"] >= 1)
        sample = asyncio.create_task(asyncio.to_thread(
            eng.admin, "/api/containers/testUser/directSC/sample",
            {"topic": "/stringEchoReq", "count": 3, "timeout": WAIT}))
        await until(lambda: stats(eng, "directSC"), lambda s: direct(s)["claims"] == 0)
        got = []
        while not sample.done():
            got.append(await echo(r, f"s{len(got)}", timeout=2.0))
            assert len(got) < 200
        msgs = await sample
        assert len(msgs) == 3 and all(m["data"].startswith("s") for m in msgs)
        assert any(got), "the node stopped echoing while the sample watched"
        await until(lambda: stats(eng, "directSC"), lambda s: direct(s)["claims"] >= 1)
        assert await echo(r, "after", timeout=5.0) is not None


async def test_kill_9_of_a_node_with_direct_links(eng):
    """The node dies with its direct links: the robot endpoint's claim ends with the link, the
    respawned node gets new routes, and echoes resume."""
    async with RawRobot(eng.master_url, "directK") as r:
        ctag = "directKC"
        await topic_echo(r, ctag, [{"nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py", "respawn": True}],
                         "/stringEchoReq", "/stringEchoResp")
        await first_echo(r, "warm")
        s = await until(lambda: stats(eng, ctag), lambda s: direct(s)["claims"] >= 1 and direct(s)["routes"] >= 1)
        pid = s["per_node"]["echo"]["pid"]
        opened = direct(s)["links_opened"]
        os.kill(pid, signal.SIGKILL)
        s = await until(lambda: stats(eng, ctag),
                        lambda s: s["per_node"]["echo"]["pid"] not in (None, pid) and direct(s)["claims"] >= 1
                        and direct(s)["routes"] >= 1)
        assert direct(s)["links_opened"] > opened
        await first_echo(r, "again")
        for i in range(20):
            assert await echo(r, f"k{i}", timeout=5.0) is not None


async def test_bus_path_when_direct_links_are_off(tmp_path):
    """RCE_DIRECT_LINKS=0: the same echo, every message through the environment."""
    from rce.tools.launch import start_engine
    e = await asyncio.to_thread(start_engine, tmp_path / "engine", env={"RCE_DIRECT_LINKS": "0"})
    try:
        async with RawRobot(e.master_url, "offR") as r:
            await _echo_container(r, "offC", "Converter")
            await first_echo(r, "warm")
            before = (await asyncio.to_thread(stats, e, "offC"))["environment"]
            for i in range(20):
                assert await echo(r, f"o{i}", timeout=5.0) is not None
            after = (await asyncio.to_thread(stats, e, "offC"))["environment"]
            assert after["direct"] == {"enabled": False}
            assert after["dataplane"]["msgs_in"] - before["dataplane"]["msgs_in"] >= 20
            assert after["dataplane"]["msgs_out"] - before["dataplane"]["msgs_out"] >= 20
    finally:
        await asyncio.to_thread(e.stop)


async def test_two_subscriber_nodes_share_a_claim_and_a_survivor_misses_nothing(eng):
    """Two echo nodes (bench/packages' benchecho) subscribe /pose: both claim it (one claim set
    of 2), each gets every message once (two echoes per request), none through the
    environment. kill -9 of one: the set is incomplete, so the robot endpoint sends by the
    environment again and the survivor echoes every message; then its set of 1 goes direct."""
    async with RawRobot(eng.master_url, "direct2") as r:
        ctag = "direct2C"
        await topic_echo(r, ctag, [{"nodeTag": n, "pkg": "benchecho", "exe": "echo.py", "name": n,
                                    "args": "--type std_msgs/String --back --report 60 /pose"}
                                   for n in ("echoA", "echoB")], "/pose", "/pose_echo")
        s = await until(lambda: stats(eng, ctag),
                        lambda s: all(s["per_node"][n]["connected"] for n in ("echoA", "echoB")))
        await first_echo(r, "warm")
        s = await until(lambda: stats(eng, ctag), lambda s: direct(s)["claims"] == 2 and direct(s)["routes"] == 2)
        await asyncio.sleep(0.3)
        while True:                      # what is still coming from the warm-up
            try:
                await r.expect("DM", timeout=0.3)
            except TimeoutError:
                break
        before = s["environment"]["dataplane"]
        n = 20
        for i in range(n):
            await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": f"t{i}"}})
        got = [(await r.expect("DM", timeout=5.0, pred=lambda d: d["iTag"] == "resp"))["msg"]["data"]
               for _ in range(2 * n)]
        assert sorted(got) == sorted([f"t{i}" for i in range(n)] * 2)
        after = stats(eng, ctag)["environment"]["dataplane"]
        assert after["msgs_in"] - before["msgs_in"] < 5 and after["msgs_out"] - before["msgs_out"] < 5

        os.kill(s["per_node"]["echoA"]["pid"], signal.SIGKILL)
        for i in range(n):               # at once: the survivor echoes every one
            assert await echo(r, f"k{i}", timeout=5.0) is not None
        await until(lambda: stats(eng, ctag), lambda s: direct(s)["claims"] == 1 and direct(s)["routes"] == 1)
        for i in range(n):
            assert await echo(r, f"d{i}", timeout=5.0) is not None


async def test_echoes_keep_their_order_while_the_paths_change_under_a_stream(eng):
    """Numbered messages at 200 Hz from the moment the interfaces are up: the first go through the
    environment (whose data links are still being dialled), then the node's claim and route take
    over; two samples of /stringEchoReq end the claim and it comes back each time. Through every
    change of path, each echo comes once and in order: messages still on their way by the
    environment arrive before the direct ones behind them (the switch markers, the held route)."""
    # never shed, even on a loaded machine (maxLag=0): every message must come back
    async with RawRobot(eng.master_url, "directO", query="&maxLag=0") as r:
        ctag = "directOC"
        echoes: list[int] = []
        sent = 0

        async def send() -> None:
            nonlocal sent
            while True:
                await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "",
                                    "msg": {"data": str(sent)}})
                sent += 1
                await asyncio.sleep(0.005)

        async def read() -> None:
            while True:
                m = await r.recv(60)
                if isinstance(m, dict) and m.get("type") == "DM" and m["data"]["iTag"] == "resp":
                    echoes.append(int(m["data"]["msg"]["data"]))

        await _echo_container(r, ctag, "Converter")
        tasks = [asyncio.create_task(send()), asyncio.create_task(read())]
        try:
            await until(lambda: stats(eng, ctag), lambda s: direct(s)["claims"] >= 1 and direct(s)["routes"] >= 1)
            for _ in range(2):
                msgs = await asyncio.to_thread(eng.admin, f"/api/containers/testUser/{ctag}/sample",
                                               {"topic": "/stringEchoReq", "count": 20, "timeout": WAIT})
                assert len(msgs) == 20
                await until(lambda: stats(eng, ctag), lambda s: direct(s)["claims"] >= 1)
            n = len(echoes)
            deadline = time.monotonic() + WAIT
            while len(echoes) < n + 100:
                assert time.monotonic() < deadline, f"{len(echoes) - n} echoes of 100 after the last change"
                await asyncio.sleep(0.05)
        finally:
            for t in tasks:
                t.cancel()
        assert echoes == sorted(echoes), [(a, b) for a, b in zip(echoes, echoes[1:], strict=False) if b < a][:5]
        assert len(echoes) == len(set(echoes)), "no echo twice"
        missing = sorted(set(range(echoes[0], echoes[-1] + 1)) - set(echoes))
        assert not missing, f"lost while the paths changed: {missing[:20]}"
