"""Authenticated internal links: each probe of an unauthenticated internal link, run with real
processes; the attacker is a raw TCP client in the test.

- Control plane: a task set that cannot prove the cluster key registers nothing, declares no
  robot connected and destroys no container; the master refuses, logs and counts it, and login
  keeps sending robots to the real endpoint (a rogue can never win the least-loaded pick).
- Data plane: a raw TCP connection to a robot endpoint's or an environment's data port delivers
  nothing to another user's robot; its frames are refused and counted, a forged credential closes
  its link.
"""
from __future__ import annotations

import asyncio
import json
import re
import struct
import time
import urllib.request

import pytest

from rce.transport import cluster_auth

from rce.transport import framing

from rce.transport import rpc
from rce.transport.cluster_auth import AuthFailed, ClusterKey
from rce.tools.launch import start_engine
from wsclient import RawRobot, login

STEP = 20.0          # s, the longest any single wait may take
ECHO = {"pkg": "Test", "exe": "stringEcho.py"}


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("engine"))
    yield e
    e.stop()


def metric(url: str, name: str, **labels: str) -> float:
    """The value of Prometheus sample ``name{labels}`` at ``url`` (0 when absent)."""
    with urllib.request.urlopen(url, timeout=10) as r:
        text = r.read().decode()
    want = ",".join(f'{k}="{v}"' for k, v in labels.items())
    m = re.search(rf"^{re.escape(name)}{re.escape('{' + want + '}') if want else ''} (\S+)$", text, re.M)
    return float(m.group(1)) if m else 0.0


async def until(pred, what: str) -> None:
    deadline = time.monotonic() + STEP
    while not pred():
        assert time.monotonic() < deadline, f"never: {what}"
        await asyncio.sleep(0.05)


async def raw(addr: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    host, _, port = addr.rpartition(":")
    return await asyncio.open_connection(host.strip("[]"), int(port))


async def frames(reader: asyncio.StreamReader) -> list:
    """Every frame the peer sends until it closes the connection."""
    data = await asyncio.wait_for(reader.read(), STEP)
    return framing.FrameDecoder().feed(data)


def req(rid: int, op: str, **args) -> bytes:
    return framing.encode_control({"id": rid, "op": op, "args": args})


# -- control plane ---------------------------------------------------------------------------------------------
async def test_a_task_set_without_the_cluster_key_can_do_nothing(eng):
    metrics = eng.master_url + "metrics"
    real_ws = login(eng.master_url)["url"]
    async with RawRobot(eng.master_url, "victim") as victim:
        await victim.send("CC", {"containerTag": "vc"})
        await victim.expect("ST", STEP, lambda d: d.get("cTag") == "vc" and d.get("status") == "running")
        # the probe of old: register a robot task set, declare testUser/rogue connected, DC the victim's container
        reader, writer = await raw(f"127.0.0.1:{eng.control_port}")
        writer.write(req(1, "register", kind="robot", name="rogue", host="127.0.0.1", ws_url="ws://127.0.0.1:9/",
                         data_addr="127.0.0.1:9")
                     + req(2, "robot_connected", user="testUser", robot="rogue")
                     + req(3, "robot_request", user="testUser", robot="victim", type="DC",
                           data={"containerTag": "vc"}))
        said = await frames(reader)                # one refusal, then the master closes the connection
        assert len(said) == 1 and said[0]["auth"] == "refused"
        assert said[0]["reason"].startswith("cluster handshake: expected 'hello', got {'id': 1, 'op': 'register'")
        writer.close()
        # ... and with the handshake, but another cluster's key
        with pytest.raises(AuthFailed, match="refused us: cluster keys differ"):
            await rpc.connect("127.0.0.1", eng.control_port, cluster_key=ClusterKey.generate())
        # nothing happened: no rogue task set or robot, the container is there, the victim's session works
        state = eng.admin("/api/state")
        assert [t["name"] for t in state["tasksets"] if t["kind"] == "robot"] == \
            [t["name"] for t in state["tasksets"] if t["kind"] == "robot" and t.get("ws_url") == real_ws]
        assert {r["robot"] for r in state["robots"]} == {"victim"}
        assert [c["ctag"] for c in state["containers"]] == ["vc"]
        await victim.probe()
    # refused, counted and logged (structured)
    assert metric(metrics, "rce_master_control_refused_total", reason="malformed") >= 1
    assert metric(metrics, "rce_master_control_refused_total", reason="wrong_key") >= 1
    logged = [json.loads(line) for line in (eng.workdir / "master.log").read_text().splitlines()
              if "unauthenticated link refused" in line]
    assert {entry["reason"] for entry in logged} >= {"malformed", "wrong_key"}
    assert all(entry["listener"] == "rce-master control" and entry["peer"] for entry in logged)
    # the next robot to log in goes to the real endpoint; with the key, a link is served
    assert login(eng.master_url) == {"url": real_ws}
    peer = await rpc.connect("127.0.0.1", eng.control_port, cluster_key=eng.cluster_key)
    assert await peer.call("ping") is None
    await peer.close()


# -- data plane --------------------------------------------------------------------------------------------------
def string_msg(text: str) -> bytes:
    """A ROS 1 serialized std_msgs/String."""
    data = text.encode()
    return struct.pack("<I", len(data)) + data


async def inject(addr: str, dst: int, src: int) -> tuple[list, list]:
    """Two attacks on the data port at ``addr``: frames with no grant, and a forged grant. Returns
    what the port said to each (its nonce, then nothing: the forged one is closed on)."""
    reader, writer = await raw(addr)
    first = framing.FrameDecoder().feed(await asyncio.wait_for(reader.read(4096), STEP))
    writer.write(framing.encode_data(framing.MSG, dst, src, 0, string_msg("INJECTED")) * 3)
    forged_r, forged_w = await raw(addr)
    nonce = bytes.fromhex(framing.FrameDecoder().feed(await asyncio.wait_for(forged_r.read(4096), STEP))[0]["nonce"])
    guess = cluster_auth.grant_proof(b"\0" * 32, nonce, src, dst).hex()
    forged_w.write(framing.encode_control({"grant": [src, dst], "proof": guess})
                   + framing.encode_data(framing.MSG, dst, src, 0, string_msg("INJECTED")))
    after = await frames(forged_r)
    writer.close()
    return first, after


async def test_a_raw_data_link_delivers_nothing_to_another_users_robot(eng):
    robot_metrics = f"http://127.0.0.1:{eng.robot_ready[0]['metrics_port']}/metrics"
    async with RawRobot(eng.master_url, "dv") as r:
        await r.send("CC", {"containerTag": "dc"})
        await r.cn(addNodes=[{"containerTag": "dc", "nodeTag": "echo", **ECHO}])
        for etag, itag, itype, addr in [("dc", "req", "PublisherInterface", "/stringEchoReq"),
                                        ("dc", "resp", "SubscriberInterface", "/stringEchoResp"),
                                        ("dv", "req", "SubscriberConverter", None),
                                        ("dv", "resp", "PublisherConverter", None)]:
            await r.iface(etag, itag, itype, "std_msgs/String", addr)
        await r.send("CX", {"connect": [{"tagA": "dc/req", "tagB": "dv/req"}, {"tagA": "dc/resp", "tagB": "dv/resp"}]})
        await r.wait_up("req", "resp")
        assert set(await echo(r, "before")) == {"before"}     # the echo node is up: an injection would come back
        iid = {i["tag"]: i["iid"] for i in eng.admin("/api/interfaces")}
        env = eng.admin("/api/containers/testUser/dc/stats")["environment"]
        # straight to the robot's PublisherConverter, as if from the container's SubscriberInterface ...
        first, after = await inject(eng.robot_ready[0]["data_addr"], iid["dv/resp"], iid["dc/resp"])
        assert list(first[0]) == ["nonce"] and after == []
        # ... and into the container's bus, whose echo node would send it on to the robot
        first, after = await inject(env["data_addr"], iid["dc/req"], iid["dv/req"])
        assert list(first[0]) == ["nonce"] and after == []
        await until(lambda: metric(robot_metrics, "rce_robot_dataplane_refused") >= 3
                    and metric(robot_metrics, "rce_robot_dataplane_unauthenticated") >= 1, "the robot endpoint refused")
        plane = eng.admin("/api/containers/testUser/dc/stats")["environment"]["dataplane"]
        assert plane["refused"] >= 3 and plane["unauthenticated"] >= 1
        # the robot's own traffic goes through, and it never saw the injected messages
        assert set(await echo(r, "after")) <= {"before", "after"}


async def echo(r: RawRobot, text: str) -> list[str]:
    """Send ``text`` to the echo node (again, every 0.5 s, until it answers: it may subscribe a moment
    after the interfaces are up); the data of every DM the robot got meanwhile, up to the first echo
    of ``text``."""
    got: list[str] = []
    deadline = time.monotonic() + STEP
    while not got or got[-1] != text:
        assert time.monotonic() < deadline, f"no echo of {text!r}; got {got}"
        await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": text}})
        try:
            got.append((await r.expect("DM", 0.5, lambda d: d["iTag"] == "resp"))["msg"]["data"])
        except TimeoutError:
            continue
    return got
