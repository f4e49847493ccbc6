"""The live fleet in Foxglove's protocol: ``rce-fleet serve --foxglove-port 0 --record run.mcap`` as a process
(engine, fleet container, pymunk robots) on the lab map, 3 robots, sped up.

- Foxglove's own client (npm ``@foxglove/ws-protocol`` in Node, pinned by ``foxglove/package-lock.json``)
  subscribes to the robots' poses, decodes them with ``@foxglove/rosmsg-serialization`` from the schema
  the server advertised, publishes a goal on ``/fleet/goal`` and sees the robot take it and move.
- Bad clients (no login, the wrong subprotocol, unknown channels, a subscribe flood, a 10 MB message, a
  topic the fleet does not take) each get the protocol's ``status`` error while a good client's poses keep
  coming; the server's ``/metrics`` counts them.
- The run's MCAP file, once the fleet stops, read back with ``mcap``'s reader and ``mcap-ros1-support``'s
  decoder. (The ``mcap`` CLI and its ``doctor`` come from no registry this project installs from: not
  PyPI, npm or Debian.)
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import os
import re
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import orjson
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from tests.fleet.test_fleet_tasks_api import stop

BIN = Path(sys.executable).parent
NODE_DIR = Path(__file__).resolve().parent / "foxglove"
CLIENT = NODE_DIR / "fleet_client.mjs"
STARTS = {"Robot1": 32, "Robot2": 7, "Robot3": 63}
GOAL = 35                      # Robot1's goal: three cells east of its start
URL_RE = re.compile(r"Foxglove WebSocket: ws://127\.0\.0\.1:(\d+)/")
START_TIMEOUT_S = 90           # wall s for rce-fleet to start everything and print the Foxglove URL
LOG_POLL_S = 0.1               # wall s between reads of rce-fleet's output while waiting for the URL
NODE_TIMEOUT_MS = 40_000       # the Node client's whole run (subscribe, publish, see the robot move)
STEP_TIMEOUT_S = 10.0          # one answer from the server
ADMIN_PW = "foxglove-admin-pw"     # the first admin's (--admin-password-file): an operator may publish
SUB = "foxglove.websocket.v1"
NPM_HINT = "the Foxglove client is not installed: run `make setup` (npm ci --prefix tests/web/foxglove)"


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """``rce-fleet serve --foxglove-port 0 --record``; yields {"port", "proc", "log", "mcap", "token"} (a token
    of the page's POST /api/login, the port's credential); stopped with SIGINT."""
    d = tmp_path_factory.mktemp("foxglove")
    log, mcap = d / "serve.log", d / "run.mcap"
    (d / "admin-pw").write_text(ADMIN_PW + "\n")
    argv = [str(BIN / "rce-fleet"), "serve", "--robots", str(len(STARTS)), "--speedup", "5", "--seed", "3",
            "--grid", "8x8", "--web-port", "0", "--no-live", "--foxglove-port", "0", "--record", str(mcap),
            "--workdir", str(d / "work"), "--timeout", "600", "--admin-password-file", str(d / "admin-pw"),
            *[a for r, c in STARTS.items() for a in ("--start", f"{r}={c}")]]
    out = open(log, "wb")
    p = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                         env=dict(os.environ, RCE_LOG_JSON="1"))
    port = _wait_port(log, p)
    if port is None:
        p.kill()
        pytest.fail(f"rce-fleet serve printed no Foxglove URL:\n{log.read_text(errors='replace')[-3000:]}")
    page = re.search(r"operator page: (http://\S+?/)", log.read_text(errors="replace")).group(1)
    req = urllib.request.Request(page + "api/login", data=json.dumps({"user": "admin", "password": ADMIN_PW}).encode(),
                                 headers={"Content-Type": "application/json"}, method="POST")
    with urllib.request.urlopen(req, timeout=STEP_TIMEOUT_S) as r:
        token = json.loads(r.read())["token"]
    yield {"port": port, "proc": p, "log": log, "mcap": mcap, "token": token}
    stop(p)


def _wait_port(log: Path, proc: subprocess.Popen) -> int | None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        m = URL_RE.search(log.read_text(errors="replace"))
        if m:
            return int(m.group(1))
        if proc.poll() is not None:
            return None
        time.sleep(LOG_POLL_S)
    return None


def url(fleet, token: str | None = None) -> str:
    return f"ws://127.0.0.1:{fleet['port']}/?token={fleet['token'] if token is None else token}"


class Client:
    """A raw Foxglove client (websockets): ``channels`` by topic once advertised, ``statuses`` received."""

    def __init__(self, ws):
        self.ws, self.channels, self.statuses, self.data = ws, {}, [], asyncio.Queue()
        self.info = None
        self._task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        try:
            async for m in self.ws:
                if isinstance(m, bytes):
                    self.data.put_nowait((int.from_bytes(m[1:5], "little"), time.monotonic(), m[13:]))
                    continue
                msg = orjson.loads(m)
                if msg["op"] == "advertise":
                    self.channels.update({c["topic"]: c for c in msg["channels"]})
                elif msg["op"] == "status":
                    self.statuses.append(msg)
                elif msg["op"] == "serverInfo":
                    self.info = msg
        except ConnectionClosed:
            pass

    async def send(self, op: str, **fields) -> None:
        await self.ws.send(json.dumps({"op": op, **fields}))

    async def status(self, needle: str) -> dict:
        """The first status error whose message contains ``needle`` (within STEP_TIMEOUT_S)."""
        async with asyncio.timeout(STEP_TIMEOUT_S):
            while True:
                for s in self.statuses:
                    if needle in s["message"]:
                        assert s["level"] == 2, s
                        return s
                await asyncio.sleep(0.02)

    async def advertised(self, topic: str) -> dict:
        async with asyncio.timeout(STEP_TIMEOUT_S):
            while topic not in self.channels:
                await asyncio.sleep(0.02)
        return self.channels[topic]

    async def close(self) -> None:
        await self.ws.close()
        await self._task


async def _open(fleet, **kw) -> Client:
    return Client(await connect(url(fleet), subprotocols=[SUB], max_size=None, **kw))


def test_foxglove_client_sees_poses_and_sends_a_goal(fleet):
    """Foxglove's own client in Node: poses decoded from the advertised schema, a goal taken."""
    if not (NODE_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        pytest.fail(NPM_HINT)
    p = subprocess.run(["node", str(CLIENT), url(fleet), "Robot1", str(GOAL), str(NODE_TIMEOUT_MS)],
                       capture_output=True, text=True, timeout=NODE_TIMEOUT_MS / 1000 + 10, cwd=NODE_DIR)
    seen = json.loads(p.stdout.strip().splitlines()[-1]) if p.stdout.strip() else {}
    assert p.returncode == 0, f"{p.stderr}\n{seen}"
    assert seen["serverInfo"]["capabilities"] == ["clientPublish"]
    for r in STARTS:
        assert seen["channels"][f"/{r}/pose"] == {"encoding": "ros1", "schemaName": "geometry_msgs/PoseStamped",
                                                  "schemaEncoding": "ros1msg"}
        assert seen["channels"][f"/{r}/path"]["schemaName"] == "nav_msgs/Path"
        assert seen["poses"][r] >= 1
    assert seen["channels"]["/map"]["schemaName"] == "nav_msgs/OccupancyGrid"
    assert seen["channels"]["/fleet/places"]["schemaName"] == "visualization_msgs/MarkerArray"
    assert seen["channels"]["/fleet/state"]["schemaName"] == "fleet/FleetState"
    width, height, cells, frame = seen["mapSize"]
    assert width * height == cells > 0 and frame == "map"
    assert seen["goalTaken"] and seen["moved"] > 0.3 and seen["statuses"] == []


async def test_bad_login_and_wrong_subprotocol_are_refused(fleet):
    with pytest.raises(InvalidStatus) as e:
        await connect(url(fleet, "wrong"), subprotocols=[SUB])
    assert e.value.response.status_code == 401
    with pytest.raises(InvalidStatus) as e:
        await connect(f"ws://127.0.0.1:{fleet['port']}/", subprotocols=[SUB])
    assert e.value.response.status_code == 401 and b"bearer token" in e.value.response.body
    with pytest.raises(InvalidStatus) as e:        # a password's digest is no credential here
        digest = hashlib.sha256(ADMIN_PW.encode()).hexdigest()
        await connect(f"ws://127.0.0.1:{fleet['port']}/?userID=admin&password={digest}", subprotocols=[SUB])
    assert e.value.response.status_code == 401 and b"takes no password" in e.value.response.body
    async with connect(url(fleet), subprotocols=["foxglove.websocket.v2"]) as ws:
        msg = orjson.loads(await asyncio.wait_for(ws.recv(), STEP_TIMEOUT_S))
        assert msg["op"] == "status" and msg["level"] == 2 and SUB in msg["message"]
        with pytest.raises(ConnectionClosed):
            await asyncio.wait_for(ws.recv(), STEP_TIMEOUT_S)
        assert ws.close_code == 1002


async def test_bad_clients_get_status_errors_and_harm_no_other(fleet):
    good, bad = await _open(fleet), await _open(fleet)
    pose = await good.advertised("/Robot2/pose")
    await good.send("subscribe", subscriptions=[{"id": 7, "channelId": pose["id"]}])
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while (await good.data.get())[0] != 7:
            pass
    await bad.advertised("/fleet/state")
    # unknown channel, unknown subscription, unknown op, not JSON
    await bad.send("subscribe", subscriptions=[{"id": 1, "channelId": 999_999}])
    await bad.status("unknown channel 999999")
    await bad.send("unsubscribe", subscriptionIds=[42])
    await bad.status("unknown subscription 42")
    await bad.send("fly")
    await bad.status("unsupported op 'fly'")
    await bad.ws.send("{not json")
    await bad.status("not JSON")
    # publishing: on a channel never advertised, on a topic the fleet does not take, bytes that do not fit
    await bad.ws.send(b"\x01" + (77).to_bytes(4, "little") + b"xx")
    await bad.status("unknown client channel 77")
    await bad.send("advertise", channels=[{"id": 1, "topic": "/cmd_vel", "encoding": "ros1",
                                           "schemaName": "geometry_msgs/Twist"},
                                          {"id": 2, "topic": "/fleet/goal", "encoding": "ros1",
                                           "schemaName": "fleet/RobotGoal"}])
    await bad.ws.send(b"\x01" + (1).to_bytes(4, "little") + bytes(48))
    await bad.status("/cmd_vel: not a topic this fleet takes")
    await bad.ws.send(b"\x01" + (2).to_bytes(4, "little") + b"\x05")
    await bad.status("/fleet/goal: 1 bytes do not fit fleet/RobotGoal")
    # a 10 MB message: refused with a status, the link stays
    await bad.ws.send(b"\x01" + (2).to_bytes(4, "little") + bytes(10 * 1024 * 1024))
    await bad.status("is over the 4194304-byte limit")
    # a subscribe flood: thousands of ops, and one op over the entries' bound
    t0, before = time.monotonic(), good.data.qsize()
    for i in range(3000):
        await bad.send("subscribe", subscriptions=[{"id": 100 + i, "channelId": 500_000 + i}])
    await bad.send("subscribe", subscriptions=[{"id": i, "channelId": 1} for i in range(5000)])
    await bad.status("over the 4096 limit")
    await bad.status("unknown channel 502999")
    flood_s = time.monotonic() - t0
    # the good client's poses kept coming (5 Hz fleet state; sped up), and the bad client is still served
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while good.data.qsize() - before < 2:
            await asyncio.sleep(0.05)
    state = await bad.advertised("/fleet/state")
    await bad.send("subscribe", subscriptions=[{"id": 9, "channelId": state["id"]}])
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while (await bad.data.get())[0] != 9:
            pass
    assert not [s for s in good.statuses], good.statuses
    await good.close()
    await bad.close()
    metrics = urllib.request.urlopen(urllib.request.Request(f"http://127.0.0.1:{fleet['port']}/metrics", headers={
        "Authorization": f"Bearer {fleet['token']}"}), timeout=STEP_TIMEOUT_S).read()
    counts = dict(line.split() for line in metrics.decode().splitlines() if line and not line.startswith("#"))
    assert int(counts["rce_fleet_foxglove_status_errors"]) >= 3000 + 10, (counts, flood_s)
    assert int(counts["rce_fleet_foxglove_clients_total"]) >= 3 and "rce_fleet_foxglove_dropped" in counts


async def test_json_publish_goes_to_the_fleet(fleet):
    """A client publishing in JSON (Foxglove's Publish panel can): a block of a cell reaches the planner."""
    c = await _open(fleet)
    state = await c.advertised("/fleet/state")
    await c.send("advertise", channels=[{"id": 3, "topic": "/fleet/block", "encoding": "json",
                                         "schemaName": "fleet/CellBlock"}])
    await c.ws.send(b"\x01" + (3).to_bytes(4, "little") + json.dumps({"cell": 0, "blocked": True}).encode())
    await c.send("subscribe", subscriptions=[{"id": 1, "channelId": state["id"]}])
    from rce.messages import MessageRegistry
    from rce.node.package_path import load_package_types
    reg = MessageRegistry()
    load_package_types(reg)
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while True:
            _, _, payload = await c.data.get()
            if 0 in reg.bytes_to_json("fleet/msg/FleetState", payload)["blocked"]:
                break
    await c.ws.send(b"\x01" + (3).to_bytes(4, "little") + json.dumps({"cell": 0, "blocked": False}).encode())
    await c.close()
    assert c.statuses == []


async def test_a_pose_on_goal_pose_is_a_goal(fleet):
    """Foxglove's 3D panel "Publish pose" on /Robot3/goal_pose: the robot's goal is the cell of that point."""
    from rce.messages import MessageRegistry
    from rce.node.package_path import load_package_types
    reg = MessageRegistry()
    load_package_types(reg)
    c = await _open(fleet)
    state = await c.advertised("/fleet/state")
    await c.send("subscribe", subscriptions=[{"id": 1, "channelId": state["id"]}])
    async with asyncio.timeout(STEP_TIMEOUT_S):
        st = reg.bytes_to_json("fleet/msg/FleetState", (await c.data.get())[2])
    target = STARTS["Robot1"]              # Robot1's start: free once Robot1 left for GOAL
    row, col = divmod(target, st["cols"])  # its centre, from the grid the fleet state describes (map yaw 0)
    x, y = st["grid_x"] + (col + 0.5) * st["cell_w"], st["grid_y"] - (row + 0.5) * st["cell_h"]
    await c.send("advertise", channels=[{"id": 5, "topic": "/Robot3/goal_pose", "encoding": "json",
                                         "schemaName": "geometry_msgs/PoseStamped"}])
    pose = {"header": {"frame_id": "map"}, "pose": {"position": {"x": x, "y": y}, "orientation": {"w": 1.0}}}
    await c.ws.send(b"\x01" + (5).to_bytes(4, "little") + json.dumps(pose).encode())
    r = None
    try:
        async with asyncio.timeout(STEP_TIMEOUT_S):
            while r is None or r["goal"] != target:
                st = reg.bytes_to_json("fleet/msg/FleetState", (await c.data.get())[2])
                r = next(r for r in st["robots"] if r["robot"] == "Robot3")
    except TimeoutError:
        raise AssertionError(f"Robot3 never got goal {target}: {r}; statuses {c.statuses}") from None
    far = {"pose": {"position": {"x": 1e6, "y": 0}}}
    await c.ws.send(b"\x01" + (5).to_bytes(4, "little") + json.dumps(far).encode())
    await c.status("is outside the grid")
    await c.close()


def test_the_run_is_recorded_in_mcap(fleet):
    """Last: stop the fleet, read its MCAP back."""
    from mcap.reader import make_reader
    from mcap_ros1.decoder import DecoderFactory
    assert stop(fleet["proc"]) == 0, fleet["log"].read_text(errors="replace")[-3000:]
    path = fleet["mcap"]
    assert path.exists() and not path.with_name(path.name + ".active").exists()
    counts: dict[str, int] = {}
    last: dict = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros1"
        summary = reader.get_summary()
        assert {c.message_encoding for c in summary.channels.values()} == {"ros1"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros1msg"}
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert len(topics) == len(summary.channels)          # one channel per topic
        stamps, path_ends = [], set()
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            last[channel.topic] = decoded
            stamps.append(message.log_time)
            if channel.topic == "/Robot1/goalNodesList" and len(decoded.data):
                path_ends.add(int(decoded.data[-1]))
    assert stamps == sorted(stamps)
    assert sum(summary.statistics.channel_message_counts.values()) == sum(counts.values())
    for r in STARTS:
        assert topics[f"/{r}/amcl_pose"] == "geometry_msgs/PoseWithCovarianceStamped"
        assert counts[f"/{r}/amcl_pose"] > 10 and last[f"/{r}/amcl_pose"].header.frame_id == "map"
    assert topics["/fleet/state"] == "fleet/FleetState" and counts["/fleet/state"] > 5
    assert sorted(r.robot for r in last["/fleet/state"].robots) == sorted(STARTS)
    assert GOAL in path_ends                  # the goal the Foxglove client sent: a path to it was planned
    assert topics["/fleet/tasks"] == "fleet/TaskList"
    assert f"recorded {sum(counts.values())} message(s)" in fleet["log"].read_text(errors="replace")


def test_replay_plays_the_recording_onto_the_page(fleet, browser, tmp_path):
    """After the recording test: ``rce-fleet replay run.mcap --loop`` and the operator page, logged in as usual,
    draws the recorded fleet."""
    assert fleet["mcap"].exists(), "the recording test runs first"
    log = tmp_path / "replay.log"
    p = subprocess.Popen([str(BIN / "rce-fleet"), "replay", str(fleet["mcap"]), "--loop", "--speed", "2",
                          "--web-port", "0"], stdout=open(log, "wb"), stderr=subprocess.STDOUT,
                         start_new_session=True, env=dict(os.environ, RCE_LOG_JSON="1"))
    try:
        deadline, page_url = time.monotonic() + START_TIMEOUT_S, None
        while page_url is None and time.monotonic() < deadline and p.poll() is None:
            m = re.search(r"operator page: (http://\S+)", log.read_text(errors="replace"))
            page_url = m.group(1) if m else None
            time.sleep(LOG_POLL_S)              # polling the log: the process tells nothing else
        assert page_url, log.read_text(errors="replace")[-3000:]
        ctx = browser.new_context()
        page = ctx.new_page()
        page.goto(page_url)
        page.wait_for_function("document.querySelector('#user').value !== ''", timeout=START_TIMEOUT_S * 1000)
        page.fill("#password", "testUser")
        page.click("#login-btn")
        page.wait_for_function("fleetView.connected && fleetView.updates >= 3 && "
                               "Object.keys(fleetView.robots).length == 3", timeout=START_TIMEOUT_S * 1000)
        robots = page.evaluate("fleetView.robots")
        grid = page.evaluate("[fleetView.grid.rows, fleetView.grid.cols]")
        ctx.close()
    finally:
        code = stop(p)
    assert sorted(robots) == sorted(STARTS) and grid == [8, 8]
    assert all(r["cell"] >= 0 for r in robots.values())
    assert code == 0, log.read_text(errors="replace")[-3000:]
