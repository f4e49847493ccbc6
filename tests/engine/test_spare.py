"""A container's spare (``containerData`` ``spare: true``), against a real engine on loopback: a
master, a robot task set, a cloud container host and robot ``spare``'s own computer (``--zone
robot:spare``). The robot sends numbered ``std_msgs/String`` at 20 Hz to ``stringEcho.py`` in its
container and reads the echoes.

- the master keeps a made copy on the host the placer ranks next; a move there takes it (only the
  switch and the break), a new spare is made on the host it left, and the move back takes that:
  every message echoed once, in order;
- a spare made before the container changed (a parameter set since) is destroyed and a fresh one
  made, which the move takes;
- kill -9 of a spare's environment: the master forgets it (the container is not lost, its robot
  told nothing), makes another, and the next move takes that one;
- kill -9 of the host the container runs on: its failover takes the spare (the container runs on as
  the spare's copy on the robot's computer, nothing re-created).
"""
from __future__ import annotations

import asyncio
import time
import urllib.request
from contextlib import asynccontextmanager
from pathlib import Path

import psutil
import pytest

from rce.tools.launch import start_engine
from test_dataflow import _echo_container
from test_move import Stream, host_of
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

WAIT = 30.0
ROBOT_HOST = "spare-computer"
DATA = {"placement": "auto", "robot": "spare", "spare": True}


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("spare") / "engine", container_hosts=0)
    e.add_container_host("--name", "dc1")
    e.add_container_host("--zone", "robot:spare", "--user", "testUser", "--name", ROBOT_HOST)
    yield e
    e.stop()


async def spare_on(eng, ctag: str, host: str) -> dict:
    """The placement row of ``ctag`` once its spare is made on ``host``."""
    end = time.monotonic() + WAIT
    while True:
        rows = await asyncio.to_thread(eng.admin, "/api/placement")
        row = next(r for r in rows if r["ctag"] == ctag)
        if row.get("spare") and row["spare"].endswith(f"({host})"):
            return row
        assert time.monotonic() < end, f"no spare of {ctag} on {host}: {row.get('spare')}"
        await asyncio.sleep(0.1)


def host_process(eng, name: str) -> psutil.Process:
    """The process of ``eng``'s container host ``name`` (other engines, in other test workers, name
    theirs alike)."""
    def ours(argv: list[str]) -> bool:
        return any("rce-container" in a for a in argv) and name in argv and str(eng.workdir) in " ".join(argv)
    return next(p for p in psutil.process_iter(["cmdline"]) if ours(p.info["cmdline"] or []))


def environments(eng, host_name: str) -> dict[int, int]:
    """Container host ``host_name``'s containers, copies and spares alike: cid -> the pid of the
    environment process that serves its bus socket (``c<cid>/bus.sock``; a host also keeps an idle
    environment ready, which serves none)."""
    host = host_process(eng, host_name)
    out = {}
    for p in host.children(recursive=True):
        try:
            if "rce_container.environment" not in " ".join(p.cmdline()):
                continue
            for conn in p.net_connections("unix"):
                path = Path(conn.laddr) if isinstance(conn.laddr, str) and conn.laddr else None
                if path is not None and path.name == "bus.sock" and conn.status == psutil.CONN_NONE:
                    out[int(path.parent.name[1:])] = p.pid
        except psutil.NoSuchProcess:
            continue
    return out


async def environments_on(eng, host: str, n: int) -> None:
    """Wait until ``host`` runs ``n`` containers (copies and spares)."""
    end = time.monotonic() + WAIT
    while len(environments(eng, host)) != n:
        assert time.monotonic() < end, f"{host}: containers {environments(eng, host)}, not {n}"
        await asyncio.sleep(0.1)


@asynccontextmanager
async def robot(eng):
    """Robot ``spare`` logged in; on the way out, waits until the master let it go (the next test logs
    it in again)."""
    async with RawRobot(eng.master_url, "spare", query="&maxLag=0") as r:
        yield r
    end = time.monotonic() + WAIT
    while any(x.get("robot") == "spare" for x in await asyncio.to_thread(eng.admin, "/api/robots")):
        assert time.monotonic() < end, "robot spare still logged in"
        await asyncio.sleep(0.05)


def checked(s: Stream) -> None:
    seqs = [q for _, q in s.echoes]
    assert seqs == sorted(seqs), "echoes in order"
    assert len(seqs) == len(set(seqs)), "no echo twice"
    assert not sorted(set(range(seqs[0], seqs[-1] + 1)) - set(seqs)), "nothing lost"


async def made_with_spare(eng, r: RawRobot, ctag: str) -> dict[int, int]:
    """Container ``ctag`` made in the cloud, its spare made on the robot's computer: the robot
    computer's containers (:func:`environments`: the spare alone)."""
    await _echo_container(r, ctag, "Converter", DATA)
    await spare_on(eng, ctag, ROBOT_HOST)
    await environments_on(eng, ROBOT_HOST, 1)
    return environments(eng, ROBOT_HOST)


async def removed(eng, r: RawRobot, ctag: str) -> None:
    """DC ``ctag``: nothing of it is left on either host."""
    await r.send("DC", {"containerTag": ctag})
    await environments_on(eng, ROBOT_HOST, 0)
    await environments_on(eng, "dc1", 0)


async def replaced(eng, ctag: str, cid: int) -> None:
    """Wait until ``ctag``'s spare on the robot's computer is another than ``cid``, and ready."""
    end = time.monotonic() + WAIT
    while set(environments(eng, ROBOT_HOST)) in (set(), {cid}):
        assert time.monotonic() < end, f"spare c{cid} of {ctag} was not replaced"
        await asyncio.sleep(0.1)
    await spare_on(eng, ctag, ROBOT_HOST)


async def to_the_spare(eng, r: RawRobot, ctag: str) -> Stream:
    """Move ``ctag`` to the robot's computer while the echo stream runs: it takes its spare there,
    and every echo comes once, in order. Returns the stream."""
    s = Stream(r)
    task = asyncio.create_task(s.run())
    try:
        await s.until(10)
        moved = await asyncio.to_thread(eng.admin, f"/api/containers/testUser/{ctag}/move", {"host": ROBOT_HOST})
        assert moved["spare"] is True, moved
        n = len(s.echoes)
        await s.until(n + 20)
    finally:
        task.cancel()
    checked(s)
    return s


async def test_a_move_takes_its_spare_and_the_way_back_takes_the_next(eng):
    async with robot(eng) as r:
        await _echo_container(r, "spareEcho", "Converter", DATA)
        assert host_of(eng, "spareEcho") == "dc1"
        row = await spare_on(eng, "spareEcho", ROBOT_HOST)
        assert row["runs"].endswith("(dc1)") and row["spare"].startswith("robot:spare"), row
        s = Stream(r)
        task = asyncio.create_task(s.run())
        try:
            await s.until(10)
            for where, back in ((ROBOT_HOST, "dc1"), ("dc1", ROBOT_HOST)):
                await spare_on(eng, "spareEcho", where)
                moved = await asyncio.to_thread(eng.admin, "/api/containers/testUser/spareEcho/move", {"host": where})
                assert moved["spare"] is True, moved
                assert host_of(eng, "spareEcho") == where
                n = len(s.echoes)
                await s.until(n + 20)
                await spare_on(eng, "spareEcho", back)        # a new spare where it was
            await s.until(s.sent - s.echoes[0][1] - 2)
        finally:
            task.cancel()
        checked(s)
        with urllib.request.urlopen(eng.master_url + "metrics", timeout=10) as resp:
            metrics = resp.read().decode()
        assert "rce_master_container_spares_taken_total 2.0" in metrics
        assert "rce_master_container_spares 1.0" in metrics
        await removed(eng, r, "spareEcho")                      # its spare goes with it


async def test_a_spare_made_before_a_change_is_replaced(eng):
    async with robot(eng) as r:
        (old,) = await made_with_spare(eng, r, "staleEcho")
        await r.cn(setParam=[{"containerTag": "staleEcho", "name": "changed", "value": 1}])
        await replaced(eng, "staleEcho", old)         # the stale spare destroyed, a fresh one made
        await to_the_spare(eng, r, "staleEcho")
        await environments_on(eng, ROBOT_HOST, 1)               # the moved copy only
        await removed(eng, r, "staleEcho")


async def test_kill_9_of_a_spare_s_environment_is_forgotten_and_another_made(eng):
    async with robot(eng) as r:
        ((cid, env),) = (await made_with_spare(eng, r, "lostSpare")).items()
        psutil.Process(env).kill()
        await replaced(eng, "lostSpare", cid)         # forgotten, and another made
        assert host_of(eng, "lostSpare") == "dc1"
        state = next(c for c in await asyncio.to_thread(eng.admin, "/api/containers") if c["ctag"] == "lostSpare")
        assert state["state"] == "running", state
        s = await to_the_spare(eng, r, "lostSpare")
        told = [m for m in s.other if m.get("type") == "ST" and m["data"].get("status") == "lost"]
        assert not told, "the robot was told of a lost container: the spare is not the container"


async def test_kill_9_of_its_host_hands_the_container_to_its_spare(eng):
    """Last in this module: the cloud host goes for good."""
    async with robot(eng) as r:
        ((cid, _),) = (await made_with_spare(eng, r, "hostGone")).items()
        cloud = host_process(eng, "dc1")
        s = Stream(r)
        task = asyncio.create_task(s.run())
        try:
            await s.until(10)
            t_kill = time.monotonic()
            cloud.kill()
            n = len(s.echoes)
            await s.until(n + 20)                             # echoed again, by the spare
        finally:
            task.cancel()
        print(f"kill -9 of the container's host: the longest gap between echoes "
              f"{s.gap(t_kill - 0.5, s.echoes[-1][0]):.2f} s, its spare serving after it")
        c = next(c for c in (await asyncio.to_thread(eng.admin, "/api/state"))["containers"] if c["ctag"] == "hostGone")
        assert c["cid"] == cid and c["state"] == "running", "the spare became the container, not a re-created copy"
        assert host_of(eng, "hostGone") == ROBOT_HOST
        told = [m["data"]["status"] for m in s.other if m.get("type") == "ST" and m["data"].get("topic") == "container"]
        assert "lost" in told and told[-1] == "running", told
        assert set(environments(eng, ROBOT_HOST)) == {cid}, "nothing else was made there"
