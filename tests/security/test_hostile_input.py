"""Hostile input, one engine test per attack: each fails, and a victim robot's
traffic goes on undisturbed. Real processes on loopback, the raw wire protocol. The rules
themselves are tested sans I/O in tests/core/test_session_limits.py.

The robot task set runs with ``--expiry 2`` and ``--max-pending-binary 8 MiB``, the master with
``--max-containers 2`` (per user), so that the bounds are reached quickly."""
from __future__ import annotations

import asyncio
import json
import time
import urllib.request

import pytest

from rce.tools.launch import start_engine
from rce.protocol.frames import DEFAULT_MAX_PENDING_PARTS
from rce.protocol.limits import ER_BURST, ER_RATE, MAX_ER_TEXT, MAX_JSON_DEPTH
from security.hostile import Echoer, PeakRss, echo_ready, rss, still_served
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
MiB = 1024 * 1024
PENDING_TOTAL = 8 * MiB


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("hostile"), master_args=("--max-containers", "2"),
                     robot_args=("--expiry", "2", "--max-pending-binary", str(PENDING_TOTAL)))
    e.admin("/api/users", {"name": "mallory", "password": "mallory"})
    yield e
    e.stop()


def robot_pid(eng) -> int:
    return eng.robot_ready[0]["pid"]


def metrics(eng) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{eng.robot_ready[0]['metrics_port']}/metrics", timeout=10) as r:
        lines = r.read().decode().splitlines()
    return {k: float(v) for k, v in (ln.rsplit(" ", 1) for ln in lines if ln and not ln.startswith("#"))}


async def test_json_nested_1000_deep_gets_an_er_and_the_session_and_its_containers_stay(eng):
    async with RawRobot(eng.master_url, "deep", user="mallory", password="mallory") as r:
        await r.send("CC", {"containerTag": "deepC"})
        await r.ws.send('{"type": "DM", "data": ' + "[" * 1000 + "]" * 1000 + "}")
        assert await r.expect("ER", pred=lambda d: "nested" in d) == \
            f"JSON nested deeper than the limit of {MAX_JSON_DEPTH} levels; dropped"
        await r.send("CC", {"containerTag": "deepC"})          # the container is still there
        assert "container 'deepC' already exists" in await r.expect("ER", pred=lambda d: "deepC" in d)
        await r.probe()


async def test_bad_frames_with_big_values_to_a_robot_that_does_not_read_cost_bounded_memory_and_log(eng):
    log = eng.workdir / "robot0.log"
    async with RawRobot(eng.master_url, "victim_er") as victim, \
            RawRobot(eng.master_url, "flood", user="mallory", password="mallory") as r:
        await echo_ready(victim, "erC")
        log_before, rss_before = log.stat().st_size, rss(robot_pid(eng))
        peak = PeakRss(robot_pid(eng)).start()
        echo = Echoer(victim).start()
        big, t0 = "v" * MiB, time.monotonic()
        for i in range(150):                    # the robot does not read: its ERs pile up, or are dropped
            await r.send("CC" if i % 2 else "XX", {"containerTag": [big]} if i % 2 else {"v": big})
        await r.send("CX", {"connect": [{"tagA": "flood/a", "tagB": "flood/b"}]})     # a request: answered
        ers = []
        while "flood/a" not in (er := await r.expect("ER", timeout=60)):
            ers.append(er)
        took = time.monotonic() - t0
        grown = await peak.stop() - rss_before
        await echo.stop()
    print(f"\nER flood: {len(ers)} ERs for 150 bad 1 MiB frames in {took:.1f} s; rce-robot peak RSS "
          f"+{grown / MiB:.0f} MiB, log +{(log.stat().st_size - log_before) / 1024:.0f} KiB")
    # a burst, then the bucket's rate, and the ERs saying how many were dropped
    allowed = ER_BURST + ER_RATE * took + 5
    assert len(ers) <= allowed, (len(ers), took)
    assert max(len(e.encode()) for e in ers) <= MAX_ER_TEXT + 40
    if allowed < 150:                           # the flood outran the bucket (a loaded machine sends slower)
        assert any("were dropped" in e for e in ers), ers[-3:]
    assert grown < 100 * MiB, f"rce-robot grew {grown / MiB:.0f} MiB"
    assert log.stat().st_size - log_before < 1 * MiB
    assert metrics(eng)["rce_robot_errors_dropped_total"] >= 150 - len(ers)     # each bad frame: an ER, or counted


async def test_pending_binary_parts_are_capped_in_number_and_in_bytes_and_expire_cheaply(eng):
    # (expiry's cost, O(expired), is timed in tests/core/test_session_limits.py)
    async with RawRobot(eng.master_url, "bystander_bin") as bystander, \
            RawRobot(eng.master_url, "parts", user="mallory", password="mallory") as r, \
            RawRobot(eng.master_url, "parts2", user="mallory", password="mallory") as r2:
        for i in range(DEFAULT_MAX_PENDING_PARTS + 200):          # small orphan parts
            await r.ws.send(f"{i:032x}".encode() + b"x")
        er = await r.expect("ER", timeout=30, pred=lambda d: "binary parts already wait" in d)
        assert f"{DEFAULT_MAX_PENDING_PARTS} binary parts already wait for their message (the limit)" in er
        for i in range(3):                                        # 3 MiB parts: 2 fit the endpoint's 8 MiB
            await r2.ws.send(f"{i:032x}".encode() + b"y" * (3 * MiB))
        er = await r2.expect("ER", timeout=30, pred=lambda d: "on this endpoint" in d)
        assert f"exceed {PENDING_TOTAL} bytes" in er
        assert metrics(eng)["rce_robot_pending_binary_refused"] >= 1
        # they expire (--expiry 2): the count goes back to 0 and the parts' ERs say so
        await r.expect("ER", timeout=30, pred=lambda d: "expired after 2 s" in d)
        for _ in range(100):
            if metrics(eng)["rce_robot_pending_binary_bytes"] == 0:
                break
            await asyncio.sleep(0.1)      # polling a metric, with a deadline
        assert metrics(eng)["rce_robot_pending_binary_bytes"] == 0
        await bystander.probe()
        await still_served(r)


async def test_a_big_dm_of_many_values_is_parsed_off_the_loop_while_others_echo(eng):
    async with RawRobot(eng.master_url, "victim_big") as victim, \
            RawRobot(eng.master_url, "bigdm", user="mallory", password="mallory") as r:
        await echo_ready(victim, "bigC")
        before = metrics(eng)["rce_robot_big_frames_parsed"]
        echo = Echoer(victim).start()
        msg = {"data": "x", "pad": list(range(2_000_000))}            # ~15 MiB of numbers: a valid DM frame
        await r.send("DM", {"iTag": "nope", "type": "std_msgs/String", "msgID": "", "msg": msg})
        assert "no interface 'nope'" in await r.expect("ER", timeout=60)
        await echo.stop()
        await r.ws.send(json.dumps(list(range(60_000))))             # refused by the worker: its ER comes back
        assert "message must be a JSON object, got list" in await r.expect("ER", timeout=60)
        assert metrics(eng)["rce_robot_big_frames_parsed"] == before + 2


async def test_per_user_container_quota_gives_a_clear_er(eng):
    for _ in range(300):              # mallory's containers of the tests before are gone (their robots left)
        if not [c for c in eng.admin("/api/containers") if c["user"] == "mallory"]:
            break
        await asyncio.sleep(0.1)      # polling the master, with a deadline
    async with RawRobot(eng.master_url, "quota", user="mallory", password="mallory") as r:
        for ctag in ("q1", "q2"):
            await r.send("CC", {"containerTag": ctag})
        await r.send("CC", {"containerTag": "q3"})
        er = await r.expect("ER", timeout=60, pred=lambda d: "q3" in d or "quota" in d)
        assert "quota exceeded: user 'mallory' already has 2 containers" in er and "--max-containers" in er
        async with RawRobot(eng.master_url, "other_user") as other:          # testUser has its own quota
            await other.send("CC", {"containerTag": "q1"})
            await other.send("DC", {"containerTag": "q1"})
            await other.probe()
        await r.send("DC", {"containerTag": "q1"})
        await r.send("CC", {"containerTag": "q3"})                           # room again
        await r.send("DC", {"containerTag": "nope"})
        assert "container 'nope' does not exist" in await r.expect("ER", timeout=60, pred=lambda d: "nope" in d)
