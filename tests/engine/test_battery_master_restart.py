"""A robot's charge reaches a master that restarted: real processes on loopback. A robot publishes
a ``sensor_msgs/BatteryState`` once and the placer sees its charge; the master is killed (SIGKILL)
and started again on the same state file and ports. The new master keeps no charges, and the robot
publishes none after the restart: its endpoint tells the charge again once it has registered."""
from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from rce.tools.launch import start_engine
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
WAIT = 30.0     # s for a charge to reach the master (the endpoint looks every 0.25 s)


@pytest.fixture
def engine(tmp_path: Path):
    e = start_engine(tmp_path / "engine")
    yield e
    e.stop()


def charge(e, ctag: str) -> float | None:
    """The charge the placer holds for the robot of container ``ctag`` (None: none yet, or the
    master is still starting)."""
    try:
        rows = e.admin("/api/placement")
    except OSError:
        return None
    return next((x["battery"] for x in rows if x["ctag"] == ctag), None)


async def wait_charge(e, ctag: str, r: RawRobot, dm: dict | None) -> list:
    """Until the placer holds a charge for ``ctag``'s robot: send ``dm`` (if any) every look; the
    endpoint's errors meanwhile (an ER before the interface is there)."""
    loop = asyncio.get_running_loop()
    end, errors = loop.time() + WAIT, []
    while charge(e, ctag) is None:
        assert loop.time() < end, f"no charge for {ctag}'s robot within {WAIT} s: {errors[-3:]}"
        if dm is not None:
            await r.send("DM", dm)
        errors += await r.errors_within(0.2)
    return errors


async def test_a_master_that_restarted_learns_the_charge_without_a_new_reading(engine):
    async with RawRobot(engine.master_url, "rb") as r:
        await r.send("CC", {"containerTag": "planner", "containerData": {"deadline_ms": 100, "robot": "rb"}})
        await r.expect("ST", pred=lambda d: d.get("cTag") == "planner" and d.get("status") == "running")
        await r.cn(addInterfaces=[{"endpointTag": "rb", "interfaceTag": "battery",
                                   "interfaceType": "SubscriberConverter", "className": "sensor_msgs/BatteryState"}])
        await wait_charge(engine, "planner", r, {"iTag": "battery", "type": "sensor_msgs/BatteryState", "msgID": "",
                                                 "msg": {"voltage": 24.1, "percentage": 0.15, "present": True}})
        assert charge(engine, "planner") == 15.0

        engine.kill_master()
        engine.restart_master()
        errors = await wait_charge(engine, "planner", r, None)      # no new reading: the endpoint tells it again
        assert charge(engine, "planner") == 15.0
        assert not errors
