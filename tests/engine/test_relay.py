"""Relays (docs/relays.md) in network namespaces the test makes (root; deleted after, also on failure):
the cloud (the real engine) in the root namespace; leaders L1 and L2 with uplinks to it, each running
``rce-ros --relay-port``; a follower F with links only to L1 and L2 (and a direct link to the cloud that
is down until the test brings it up) running ``rce-ros --relays L1,L2`` with a converter echo through
a container's stringEcho.py. Every robot is a real rce-ros process in its namespace; the test talks
to F's local bus (a Unix socket: shared across network namespaces).

- F logs in and works through L1; the master knows it (admin API, rce-console's columns, metrics);
  L1 refuses a target outside the cloud (403) and a follower past ``--relay-max`` (503).
- F's link to L1 goes dark (L1's end down: F's packets are lost without an error): F notices by its
  pings, resumes through L2, then through its direct link once it comes up; a 10 Hz numbered stream
  echoed through the container arrives exactly once and in order, and the container stays.
- With TLS end to end, a relay (a recording CONNECT relay owned by the test) sees only TLS records:
  no password, user, robot, token or payload; replaying what it saw to the cloud opens no session.
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import sys

import pytest

import rce.node
from rce.tools.launch import start_engine
from rce.tools.netlab import NetLab, RelayTopology
from rce_client.tunnel import answer, parse_request
from nsrobot import WAIT, RosRun, echo_config

pytestmark = pytest.mark.asyncio

RELAY_PORT = 9100
RATE = 10.0                  # Hz of the numbered stream


@pytest.fixture
def topo():
    with NetLab("rlt") as lab:
        yield RelayTopology.make(lab)


@pytest.fixture
def cloud(topo, tmp_path):
    e = start_engine(tmp_path / "engine", master_args=("--bind", "0.0.0.0"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", topo.cloud_ip))
    yield e
    e.stop()


def master_url(engine, topo) -> str:
    return f"http://{topo.cloud_ip}:{engine.http_port}/"


def leader_config(url: str, robot: str) -> dict:
    return {"url": url, "userID": "testUser", "password": "testUser", "robotID": robot}


def follower_config(url: str) -> dict:
    return echo_config(url, "F")


async def wait_until(check, what: str) -> None:
    """Poll ``check()`` (a state the test cannot be told of: the master's view) until true."""
    async with asyncio.timeout(WAIT):
        while not check():
            await asyncio.sleep(0.1)        # polling the admin API, not a synchronisation stand-in
    assert check(), what


def robot_row(engine, robot: str) -> dict | None:
    return next((r for r in engine.admin("/api/robots") if r["robot"] == robot), None)


async def tunnel_statuses(topo: RelayTopology, targets: list[str]) -> list[list]:
    """From F's namespace, open a CONNECT tunnel through L1 to each ``host:port``: [status, reason] each."""
    script = ("import asyncio, json, sys\n"
              "from rce_client.tunnel import TunnelRefused, open_tunnel, split_hostport\n"
              "async def main():\n"
              "    out = []\n"
              "    for t in sys.argv[2:]:\n"
              "        try:\n"
              "            sock, name = await open_tunnel(split_hostport(sys.argv[1], 'relay'), "
              "split_hostport(t, 'target'), 5)\n"
              "            out.append([200, name]); sock.close()\n"
              "        except TunnelRefused as e:\n"
              "            out.append([e.status, e.reason])\n"
              "    print(json.dumps(out))\n"
              "asyncio.run(main())\n")
    proc = await asyncio.create_subprocess_exec(
        *topo.lab.wrap("f", [sys.executable, "-c", script, f"{topo.f_l1.a_ip}:{RELAY_PORT}", *targets]),
        stdout=asyncio.subprocess.PIPE)
    out, _ = await asyncio.wait_for(proc.communicate(), WAIT)
    return json.loads(out)


async def start_robots(topo, cloud, tmp_path, relay_max: int = 4) -> tuple[RosRun, RosRun, RosRun]:
    url = master_url(cloud, topo)
    l1 = await RosRun.start(topo.lab, "l1", leader_config(url, "L1"), tmp_path, "--relay-port", str(RELAY_PORT),
                            "--relay-max", str(relay_max))
    l2 = await RosRun.start(topo.lab, "l2", leader_config(url, "L2"), tmp_path, "--relay-port", str(RELAY_PORT))
    for leader in (l1, l2):
        await leader.wait_line("relaying for nearby robots")
    f = await RosRun.start(topo.lab, "f", follower_config(url), tmp_path, "--relays",
                           f"{topo.f_l1.a_ip}:{RELAY_PORT},{topo.f_l2.a_ip}:{RELAY_PORT}")
    await f.wait_line("rce-ros: ready")
    return l1, l2, f


async def test_follower_reaches_the_cloud_through_a_relay(topo, cloud, tmp_path):
    l1, l2, f = await start_robots(topo, cloud, tmp_path, relay_max=1)
    node = None
    try:
        assert "through relay L1" in await f.wait_line("rce-ros: connected to")
        topo.lab.shape(topo.up1, "b", rate="1gbit", dscp=True)       # a class per DSCP mark on L1's uplink
        node = await rce.node.init_node("tester", bus=str(f.bus), argv=[])
        got: asyncio.Queue = asyncio.Queue()
        await node.subscriber("/resp", "std_msgs/String", lambda m: got.put_nowait(m.data))
        pub = await node.publisher("/req", "std_msgs/String")
        async with asyncio.timeout(WAIT):
            while got.empty():              # the first messages may precede the subscription's path
                await pub.publish({"data": "over the relay"})
                try:
                    await asyncio.wait_for(got.get(), 1.0)
                    break
                except asyncio.TimeoutError:
                    continue

        # what L1 relays leaves on its uplink marked CS1 (lower effort), in the class behind L1's own traffic
        assert topo.lab.class_bytes(topo.up1, "b")["1:30"] > 0      # CS1's class

        row = robot_row(cloud, "F")
        assert row["relay"] == "L1" and row["relay_since"] >= row["since"]
        assert robot_row(cloud, "L1")["relay"] == ""
        metrics = await asyncio.to_thread(_get, cloud.master_url + "metrics")
        assert "rce_master_robots_relayed 1.0" in metrics and "rce_master_robots_relaying 1.0" in metrics
        assert 'rce_master_robot_relay{relay="L1",robot="F",user="testUser"} 1.0' in metrics

        # L1 carries F already (--relay-max 1) and never tunnels outside the cloud
        statuses = await tunnel_statuses(topo, [f"{topo.cloud_ip}:{cloud.robot_ready[0]['ws_port']}",
                                                f"{topo.up1.b_ip}:22",
                                                f"{topo.f_l2.a_ip}:{RELAY_PORT}"])
        assert [s[0] for s in statuses] == [503, 403, 403], statuses
        assert "full" in statuses[0][1] and "only relays to the cloud" in statuses[1][1]
    finally:
        if node is not None:
            await node.close()
        for r in (f, l1, l2):
            await r.stop()


def _get(url: str) -> str:
    import urllib.request
    with urllib.request.urlopen(url, timeout=10) as resp:
        return resp.read().decode()


class Stream:
    """A numbered stream published on F's bus at :data:`RATE` Hz and what comes back from the echo."""

    def __init__(self, node):
        self.node, self.sent, self.got = node, 0, []
        self.new = asyncio.Event()

    async def start(self) -> None:
        await self.node.subscriber("/resp", "std_msgs/String", self._on, queue_size=10000)
        self.pub = await self.node.publisher("/req", "std_msgs/String")
        self.task = asyncio.ensure_future(self._run())

    def _on(self, msg) -> None:
        self.got.append(int(msg.data))
        self.new.set()

    async def _run(self) -> None:
        while True:
            await self.pub.publish({"data": str(self.sent)})
            self.sent += 1
            await asyncio.sleep(1 / RATE)   # the stream's period, a timer

    async def wait_count(self, n: int) -> None:
        async with asyncio.timeout(WAIT):
            while len(self.got) < n:
                self.new.clear()
                await self.new.wait()

    async def stop(self) -> None:
        self.task.cancel()
        await asyncio.gather(self.task, return_exceptions=True)


async def test_follower_switches_relays_with_nothing_lost(topo, cloud, tmp_path):
    l1, l2, f = await start_robots(topo, cloud, tmp_path)
    node = await rce.node.init_node("tester", bus=str(f.bus), argv=[])
    try:
        cid = next(c["cid"] for c in cloud.admin("/api/containers") if c["ctag"] == "cF")
        stream = Stream(node)
        await stream.start()
        await stream.wait_count(1)
        first = stream.got[0]               # messages before the interfaces' path was whole are not echoed
        await stream.wait_count(20)
        assert robot_row(cloud, "F")["relay"] == "L1"

        # L1 drives out of range: its end of the link goes down, F's packets vanish without an error
        mark = len(f.lines)
        topo.lab.set_up(topo.f_l1, False, side="a")
        assert "through relay L2" in await f.wait_line("rce-ros: session resumed", after=mark)
        await wait_until(lambda: robot_row(cloud, "F")["relay"] == "L2", "the master sees F through L2")
        n = len(stream.got)
        await stream.wait_count(n + 20)

        # F's own link comes back: it leaves the relay
        mark = len(f.lines)
        topo.direct(True)
        assert "on its own path" in await f.wait_line("rce-ros: session resumed", after=mark)
        await wait_until(lambda: robot_row(cloud, "F")["relay"] == "", "the master sees F direct")
        n = len(stream.got)
        await stream.wait_count(n + 20)

        await stream.stop()
        await stream.wait_count(stream.sent - first)
        assert stream.got == list(range(first, stream.sent)), "every message echoed once, in order"
        assert [c["cid"] for c in cloud.admin("/api/containers") if c["ctag"] == "cF"] == [cid]
        assert not [line for line in f.lines if "moved" in line or "closed" in line]
    finally:
        await node.close()
        for r in (f, l1, l2):
            await r.stop()


class SpyRelay:
    """A relay that records every byte it carries (what a relay could see), owned by the test."""

    def __init__(self):
        self.tunnels: list[tuple[tuple[str, int], bytearray, bytearray]] = []   # (target, up, down)

    async def start(self, host: str) -> int:
        self.server = await asyncio.start_server(self._serve, host, 0)
        return self.server.sockets[0].getsockname()[1]

    async def _serve(self, reader, writer) -> None:
        target = parse_request(await reader.readuntil(b"\r\n\r\n"))
        up_r, up_w = await asyncio.open_connection(*target)
        rec = (target, bytearray(), bytearray())
        self.tunnels.append(rec)
        writer.write(answer(200, name="spy"))

        async def pipe(src, dst, into: bytearray) -> None:
            while data := await src.read(65536):
                into += data
                dst.write(data)
                await dst.drain()
            dst.close()
        await asyncio.gather(pipe(reader, up_w, rec[1]), pipe(up_r, writer, rec[2]), return_exceptions=True)

    async def close(self) -> None:
        self.server.close()


@pytest.fixture
def tls_cloud(topo, tmp_path):
    e = start_engine(tmp_path / "engine", master_args=("--bind", "0.0.0.0"), tls=True,
                     tls_hosts=(topo.cloud_ip, "127.0.0.1"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", topo.cloud_ip))
    yield e
    e.stop()


def session_lines(engine) -> int:
    """Robot sessions the endpoint opened or resumed, from its log."""
    text = (engine.workdir / "robot0.log").read_text(errors="replace")
    return text.count('"robot connected"') + text.count('"robot resumed"')


async def test_relay_cannot_read_or_forge_the_session(topo, tls_cloud, tmp_path):
    cloud = tls_cloud
    topo.lab.set_up(topo.f_cloud, True)         # F reaches the spy's address on that link, not the cloud
    spy = SpyRelay()
    port = await spy.start(topo.f_cloud.a_ip)
    url = f"https://{topo.cloud_ip}:{cloud.http_port}/"
    f = await RosRun.start(topo.lab, "f", follower_config(url), tmp_path, "--relays", f"{topo.f_cloud.a_ip}:{port}",
                           "--ca-file", str(cloud.ca_file))
    node = None
    try:
        await f.wait_line("rce-ros: ready")
        assert robot_row(cloud, "F")["relay"] == "spy"
        node = await rce.node.init_node("tester", bus=str(f.bus), argv=[])
        stream = Stream(node)
        await stream.start()
        await stream.wait_count(5)
        await stream.stop()

        # the relay saw TLS records only: neither the credentials, the session nor the payload
        assert {t[0][1] for t in spy.tunnels} == {cloud.http_port, cloud.robot_ready[0]["ws_port"]}
        secrets = [b"testUser", hashlib.sha256(b"testUser").hexdigest().encode(), b"robotID", b"session",
                   b'"seq"', b"std_msgs", b"stringEcho"]
        for target, up, down in spy.tunnels:
            assert up[:2] == b"\x16\x03" and down[:2] == b"\x16\x03", "both directions start with a TLS handshake"
            for secret in secrets:
                assert secret not in up and secret not in down, (target, secret)

        # replaying what it saw opens no session and disturbs none
        before = session_lines(cloud)
        for target, up, _ in [t for t in spy.tunnels if t[0][1] == cloud.robot_ready[0]["ws_port"]]:
            reader, writer = await asyncio.open_connection(*target)
            writer.write(bytes(up))
            await writer.drain()
            answer_bytes = await asyncio.wait_for(reader.read(), WAIT)     # the endpoint closes the connection
            writer.close()
            assert b"101 Switching" not in answer_bytes
        assert session_lines(cloud) == before
        stream = Stream(node)
        await stream.start()
        await stream.wait_count(3)              # F's own session goes on
        await stream.stop()
        assert robot_row(cloud, "F")["relay"] == "spy"
    finally:
        if node is not None:
            await node.close()
        await f.stop()
        await spy.close()
