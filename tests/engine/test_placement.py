"""Zones and the placer against a real engine on loopback: a master, a robot task set, a cloud
container host and the container host of robot ``r1``'s own computer (``--zone robot:r1 --user
testUser``).

- a container that asks nothing is placed on a shared host, never on a robot's computer;
- ``placement: robot`` runs on the robot's computer; another user's robot of the same name is refused;
- ``auto`` starts in the cloud; the placer's advice (``rce-console placement``) weighs the cloud
  through the robot's measured link and the robot's computer, and says why; a pin shows;
- zones, capacity and load show in ``rce-console tasksets`` and the master's metrics;
- the robot's charge reaches the placer from the ``sensor_msgs/BatteryState`` it publishes.
"""
from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.tools.launch import start_engine
from rce_client.connection import Connection
from wsclient import RawRobot

BIN = Path(sys.executable).parent
WAIT = 30.0


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("placement"), container_hosts=1)
    e.add_container_host("--zone", "robot:r1", "--user", "testUser", "--name", "r1-computer")
    e.admin("/api/users", {"name": "bob", "password": "bob-password"})
    yield e
    e.stop()


def console(eng, *args) -> str:
    p = subprocess.run([str(BIN / "rce-console"), "--master", eng.master_url, *args], capture_output=True, text=True,
                       env=eng.env, timeout=60)
    assert p.returncode == 0, p.stderr
    return p.stdout


def host_of(eng, user: str, ctag: str) -> str:
    return next(c["host"] for c in eng.admin("/api/containers") if (c["user"], c["ctag"]) == (user, ctag))


async def create(r: RawRobot, ctag: str, **data) -> dict:
    await r.send("CC", {"containerTag": ctag, **({"containerData": data} if data else {})})
    return await r.expect("ST", pred=lambda d: d.get("cTag") == ctag and d.get("status") == "running")


@pytest.mark.asyncio
async def test_zones_keep_robot_computers_to_their_robot(eng):
    # r1 stays connected to the end: the containers it owns are destroyed once it leaves
    async with RawRobot(eng.master_url, "r1") as r:
        for ctag in ("plain1", "plain2", "plain3"):
            await create(r, ctag)
            assert host_of(eng, "testUser", ctag) != "r1-computer", "a container asking nothing stays on shared hosts"
        await create(r, "onboard", placement="robot", robot="r1")
        assert host_of(eng, "testUser", "onboard") == "r1-computer"
        async with RawRobot(eng.master_url, "r1", user="bob", password="bob-password") as b:
            await b.send("CC", {"containerTag": "sneak", "containerData": {"placement": "robot", "robot": "r1"}})
            err = await b.expect("ER", pred=lambda d: "sneak" in d or "robot:r1" in d)
            assert "no container host in zone robot:r1" in err
            await b.send("CC", {"containerTag": "bad", "containerData": {"placement": "robot"}})
            err = await b.expect("ER", pred=lambda d: "placement" in d)
            assert "containerData: placement 'robot' needs 'robot'" in err
            await b.probe()                                      # the session lives on
        ts = {t["name"]: t for t in json.loads(console(eng, "--json", "tasksets")) if t["kind"] == "container"}
        assert ts["r1-computer"]["zone"] == "robot:r1" and ts["r1-computer"]["containers"] == 1
        assert {t["zone"] for n, t in ts.items() if n != "r1-computer"} == {"cloud"}
        assert "robot:r1" in console(eng, "tasksets")
        with urllib.request.urlopen(eng.master_url + "metrics", timeout=10) as resp:
            metrics = resp.read().decode()
        assert 'rce_master_host_containers{host="r1-computer",zone="robot:r1"} 1.0' in metrics
        assert 'rce_master_host_capacity_cpu{host="r1-computer",zone="robot:r1"}' in metrics


@pytest.mark.asyncio
async def test_the_placer_advises_through_the_measured_link_and_takes_a_pin(eng):
    async with RawRobot(eng.master_url, "r1") as r:
        await create(r, "auto1", deadline_ms=100, robot="r1", consumes=["scan"])
        await create(r, "plain4")
        assert host_of(eng, "testUser", "auto1") != "r1-computer", "auto starts in the cloud"
        loop = asyncio.get_running_loop()
        end = loop.time() + WAIT
        while True:                      # the robot endpoint reports the link within a second
            row = next(x for x in eng.admin("/api/placement") if x["ctag"] == "auto1")
            zones = {o["zone"]: o for o in row.get("options") or []}
            if "cloud" in zones and zones["cloud"]["link_ms"] > 0:     # weighed before the report: no link yet
                break
            assert loop.time() < end, row
            await asyncio.sleep(0.2)
        assert set(zones) == {"cloud", "robot:r1"}
        assert row["runs"].startswith("cloud") and not row["move"] and row["why"]
        out = console(eng, "placement")
        assert "auto1" in out and "cloud" in out
        plain = next(x for x in json.loads(console(eng, "--json", "placement")) if x["ctag"] == "plain4")
        assert plain["best"] == "-" and "asks no placement" in plain["why"]
        assert "pinned to robot" in console(eng, "placement", "pin", "testUser", "auto1", "robot")
        row = next(x for x in eng.admin("/api/placement") if x["ctag"] == "auto1")
        assert row["pinned"] == "robot" and "pinned to robot (user pin)" in row["why"]
        assert "unpinned" in console(eng, "placement", "pin", "testUser", "auto1", "auto")
        p = subprocess.run([str(BIN / "rce-console"), "--master", eng.master_url, "placement", "pin", "testUser",
                            "auto1", "moon"], capture_output=True, text=True, env=eng.env, timeout=60)
        assert p.returncode != 0 and "zone must be one of" in p.stderr


@pytest.mark.asyncio
async def test_the_robots_battery_state_reaches_the_placer(eng):
    async with RawRobot(eng.master_url, "rb") as r:         # a robot of its own: r1's sessions come and go above
        await create(r, "auto2", deadline_ms=100, robot="rb")
        await r.iface("rb", "battery", "SubscriberConverter", "sensor_msgs/BatteryState")
        loop = asyncio.get_running_loop()
        end = loop.time() + WAIT
        errors: list = []       # what the endpoint answered (an ER before the interface is there)
        while True:             # the endpoint tells the master within a second of a reading
            await r.send("DM", {"iTag": "battery", "type": "sensor_msgs/BatteryState", "msgID": "",
                                "msg": {"voltage": 24.1, "percentage": 0.15, "present": True}})
            row = next(x for x in eng.admin("/api/placement") if x["ctag"] == "auto2")
            if row["battery"] is not None:
                break
            assert loop.time() < end, (row, errors[-3:])
            errors += await r.errors_within(0.2)
        assert row["battery"] == 15.0
        assert row["battery_low"], "below the placer's threshold (20 %): it now weighs the robot's energy first"


@pytest.mark.asyncio
async def test_an_endpoint_on_a_robots_computer_serves_that_robot_alone_and_measures_its_uplink(eng):
    info = eng.add_robot_taskset("--zone", "robot:r3", "--user", "testUser", "--name", "r3-endpoint")
    own = f"ws://127.0.0.1:{info['ws_port']}/"

    def login(robot: str | None) -> str:
        q = "?userID=testUser&version=20130902" + (f"&robotID={robot}" if robot else "")
        with urllib.request.urlopen(eng.master_url + q, timeout=10) as resp:
            return json.loads(resp.read())["url"]
    assert login("r3") == own, "a robot with an endpoint on its own computer is handed that one"
    assert login("r1") != own and login(None) != own, "other robots, and a 2013 login, never get it"
    with pytest.raises(InvalidStatus) as err:             # another robot straight at it: refused before a session

        async with connect(f"{own}?userID=testUser&robotID=r4&password=x"):
            pass
    assert err.value.response.status_code == 403
    conn = await Connection.login_connect(eng.master_url, "testUser", "testUser", "r3")
    try:
        assert conn.ws_url == own
        await conn.create_container("near", placement="auto", robot="r3", deadline_ms=100)
        loop = asyncio.get_running_loop()
        end = loop.time() + WAIT
        while True:             # the uplink (its link to the master) is measured and told within a second
            row = next((x for x in eng.admin("/api/placement") if x["ctag"] == "near"), None)
            zones = {o["zone"]: o for o in (row or {}).get("options") or []}
            if "cloud" in zones and zones["cloud"]["link_ms"] > 0:
                break
            assert loop.time() < end, row
            await asyncio.sleep(0.2)
        assert "robot:r3" not in zones or zones["robot:r3"]["link_ms"] == 0
    finally:
        await conn.close()
