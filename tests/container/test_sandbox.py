"""The namespaced sandbox, as real processes: isolation (network, processes, other containers'
buses and topics), cgroup limits and live resizing, OOM kills reported with their reason,
per-container and per-node usage (stats and Prometheus), clean teardown; and the unconfined
fallback (``--sandbox unconfined``).

These need root (CI runs the suite as root). Without it they fail, saying so, rather than skip.
"""
from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import socket
import time
import urllib.request
from pathlib import Path

import psutil
import pytest

from rce.plumbing.errors import RCEError
from rce_container import cgroups

from .harness import (STEP, ContainerProcess, FakeMaster, has_service, kill_leftovers, make_helper_package, topic,
                      wait_gone)

pytestmark = pytest.mark.timeout(90)

NEEDS_ROOT = "the namespaced sandbox needs root; CI runs the test suite as root (run these tests as root)"


async def start_host(tmp_path: Path, *args: str, pkgs: Path | None = None,
                     env: dict | None = None) -> tuple[FakeMaster, ContainerProcess]:
    """A real rce-container (``args``) registered with a :class:`FakeMaster`; node packages from
    ``pkgs`` (default: the helper package, made in ``tmp_path``), ``env`` added to its environment."""
    master = FakeMaster()
    await master.start()
    pkgs = pkgs or make_helper_package(tmp_path / "pkgs")
    cp = ContainerProcess(tmp_path, master, {"RCE_PACKAGE_PATH": str(pkgs), **(env or {})}, args=args)
    try:
        await cp.start()
    except BaseException:
        print(cp.log_text())
        await cp.kill()
        await master.close()
        raise
    return master, cp


async def stop_host(master: FakeMaster, cp: ContainerProcess) -> None:
    try:
        await cp.kill()
    finally:
        await master.close()
        shutil.rmtree(cp.runtime_dir, ignore_errors=True)


@pytest.fixture
async def ns_rig(tmp_path):
    """A namespaced rce-container (with /metrics on an ephemeral port). Teardown (SIGTERM): exit
    0 with no process of any container and no cgroup directory of this task set left."""
    assert os.geteuid() == 0, NEEDS_ROOT
    master, cp = await start_host(tmp_path, "--sandbox", "namespaced", "--metrics-port", "0")
    try:
        assert master.registration["sandbox"] == "namespaced"
        scope = (await master.call("stats"))["scope"]
        bases = [Path(b) for b in cgroups.host_layout(scope).bases.values()]
        yield master, cp
        pids = [s["pid"] for s in master.statuses if s.get("pid")]
        assert await cp.terminate() == 0, cp.log_text()       # (a test may have stopped it already)
        alive = await wait_gone(pids, 5)
        kill_leftovers(alive)
        assert not alive, f"node processes survived shutdown: {alive}"
        assert not [b for b in bases if b.exists()], "the task set's cgroup directories survived shutdown"
    except BaseException:
        print(cp.log_text())
        raise
    finally:
        await stop_host(master, cp)


async def create(master, cid, ctag, group=None, **limits) -> dict:
    return await master.call("create_container", cid=cid, user="u", ctag=ctag, group=group,
                             limits={"cpu": None, "memory": None, "pids": None, "size": None, "bandwidth": None,
                                     **limits})


async def add_node(master, cid, ntag, pkg="Test", exe="stringEcho.py", args="", respawn=None, name=None) -> dict:
    return await master.call("add_node", cid=cid, ntag=ntag, pkg=pkg, exe=exe, args=args, name=name,
                             namespace=None, respawn=respawn)


def echo_ready(node: str):
    return lambda d: (f"/{node}" in topic(d, "/stringEchoReq")["subscribers"]
                      and has_service(d, "/stringEchoService"))


async def wait_stdout(master, cid, ntag) -> list[str]:
    deadline = time.monotonic() + STEP
    while not (out := (await master.call("logs", cid=cid, ntag=ntag))["stdout"]):
        assert time.monotonic() < deadline, \
            f"node {ntag} printed nothing: {await master.call('logs', cid=cid, ntag=ntag)}"
        await asyncio.sleep(0.05)
    return out


class TcpServer:
    """A TCP server on the host's loopback that counts connections."""

    def __init__(self) -> None:
        self.accepted = 0

    async def __aenter__(self):
        async def accept(_r, w):
            self.accepted += 1
            w.close()
        self.server = await asyncio.start_server(accept, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc):
        self.server.close()


def bus_socket(cp: ContainerProcess, cid: int) -> str:
    return str(cp.runtime_dir / f"c{cid}" / "bus.sock")


async def test_a_node_reaches_nothing_but_its_container_bus(ns_rig):
    master, cp = ns_rig
    # A and B share a group (one bus, separate sandboxes); C is on its own.
    a, b, c = await asyncio.gather(create(master, 1, "A", group="g"), create(master, 2, "B", group="g"),
                                   create(master, 3, "C"))
    assert a["sandbox"] == b["sandbox"] == c["sandbox"] == "namespaced"
    assert a["data_addr"] == b["data_addr"] != c["data_addr"]
    secret = (await add_node(master, 2, "echoB", name="echoB"))["pid"]       # B's node: topics on the group bus
    await master.wait_bus(2, echo_ready("echoB"))
    host_sock = str(cp.runtime_dir / "host.sock")
    async with TcpServer() as srv:
        # each probe tries its group mate's or the other container's bus socket and the host's control socket
        await add_node(master, 1, "probe", pkg="CTest", exe="probe.py",
                       args=[str(srv.port), bus_socket(cp, 2), bus_socket(cp, 3), host_sock])
        await add_node(master, 3, "probe", pkg="CTest", exe="probe.py",
                       args=[str(srv.port), bus_socket(cp, 1), bus_socket(cp, 2), host_sock])
        in_a = json.loads((await wait_stdout(master, 1, "probe"))[0])
        in_c = json.loads((await wait_stdout(master, 3, "probe"))[0])
        await asyncio.sleep(0.1)
        assert srv.accepted == 0, "a namespaced node reached a TCP server on the host's loopback"
    for seen, cid in ((in_a, 1), (in_c, 3)):
        # network: a namespace of its own with only lo; the host's loopback is not there
        assert seen["tcp"] in ("ECONNREFUSED", "ENETUNREACH"), seen["tcp"]
        assert seen["links"] == ["lo"]
        # its own bus only: other containers' sockets and the host's control socket are hidden
        assert seen["own_bus"] == "ok"
        assert set(seen["unix"].values()) == {"ENOENT"}, seen["unix"]
        assert seen["runtime_dir"] == [f"c{cid}"]
        # processes: PID 1 is the container's init, the rest is the container's own (its zygote)
        cmdlines = seen["procs"].values()
        assert "nsinit.py" in seen["procs"]["1"]
        assert all("nsinit.py" in cl or "probe.py" in cl or "rce_container.zygote" in cl for cl in cmdlines), \
            seen["procs"]
        assert not any("stringEcho" in cl for cl in cmdlines), "a node sees a process of another container"
        assert len(seen["procs"]) <= 3
        # it cannot undo the sandbox: no CAP_SYS_ADMIN; cgroupfs is read-only and not its uid's
        # (the kernel names the permission check, EACCES, before the read-only mount, EROFS)
        assert seen["cap_sys_admin"] is False
        assert seen["cgroup_escape"] and set(seen["cgroup_escape"].values()) <= {"EROFS", "EACCES"}, \
            seen["cgroup_escape"]
    assert in_a["hostname"] == "A" and in_c["hostname"] == "C"
    # topics: A shares B's bus (same group); C sees none of it
    assert {"/stringEchoReq", "/stringEchoResp"} <= set(in_a["topics"])
    assert not any(t.startswith("/stringEcho") for t in in_c["topics"]), in_c["topics"]
    # the host sees the nodes (nsenter pid -> node), each container in a PID namespace of its own
    ns = {cid: (await master.call("stats", cid=cid))["sandbox_info"]["namespaces"] for cid in (1, 2, 3)}
    assert len({n["pid"] for n in ns.values()}) == 3 and len({n["net"] for n in ns.values()}) == 3
    assert psutil.Process(secret).is_running()


async def test_limits_resize_usage_and_metrics(ns_rig):
    master, cp = ns_rig
    res = await create(master, 4, "lim", cpu=0.25, memory=200, pids=64, size=1)   # size: the original's class
    assert res["sandbox"] == "namespaced"
    info = (await master.call("stats", cid=4))["sandbox_info"]
    files = info["cgroup"]["files"]
    if info["cgroup"]["version"] == 1:
        assert files["cpu.cfs_quota_us"] == "25000" and files["cpu.cfs_period_us"] == "100000"
        assert files["memory.limit_in_bytes"] == str(200 << 20)
        assert files.get("memory.memsw.limit_in_bytes", str(200 << 20)) == str(200 << 20)
    else:
        assert files["cpu.max"] == "25000 100000" and files["memory.max"] == str(200 << 20)
    assert files["pids.max"] == "64"
    for d in info["cgroup"]["dirs"]:        # what the issue names: a directory per container
        assert d.endswith("/c4") and Path(d).is_dir()

    echo = (await add_node(master, 4, "echo", name="echo"))["pid"]
    spin = (await add_node(master, 4, "spin", pkg="CTest", exe="spin.py"))["pid"]
    await master.wait_bus(4, echo_ready("echo"))
    for _ in range(3):
        assert await master.call("bus_publish", cid=4, topic="/stringEchoReq", type="std_msgs/String",
                                 msg={"data": "x" * 10}) == {"delivered": 1}
    await master.call("stats", cid=4)
    await asyncio.sleep(1.5)
    s = await master.call("stats", cid=4)
    # the CPU limit holds: a busy loop gets at most about a quarter of a core, and is throttled
    assert 1 < s["per_node"]["spin"]["cpu_percent"] < 40, s["per_node"]["spin"]
    assert 1 < s["cpu_percent"] < 45
    assert s["cpu"]["throttled"] > 5
    assert s["processes"] >= 5          # unshare, init, the zygote and its nsenter, two (forked) nodes
    assert s["rss_mib"] > s["per_node"]["echo"]["rss_mib"] > 5
    assert s["memory"]["limit_mib"] == 200 and s["memory"]["usage_mib"] > 0
    e = s["per_node"]["echo"]
    assert e["running"] and e["pid"] == echo and e["processes"] >= 1 and e["connected"]   # forked: no nsenter
    assert e["msgs_out"] == 3 and e["msgs_in"] == 3 and e["bytes_in"] == e["bytes_out"] > 30   # in = published
    assert s["limits"] == {"cpu": 0.25, "memory": 200, "pids": 64, "size": 1}

    # resize while running: new files, same processes, still answering
    r = await master.call("resize_container", cid=4, limits={"cpu": 1.5, "memory": 300, "pids": 100})
    assert r["limits"] == {"cpu": 1.5, "memory": 300, "pids": 100, "size": 1}
    files = (await master.call("stats", cid=4))["sandbox_info"]["cgroup"]["files"]
    assert files.get("cpu.cfs_quota_us", files.get("cpu.max", "").split(" ")[0]) == "150000"
    assert files.get("cpu.shares", files.get("cpu.weight")) in ("1536", "150")   # 1.5 cores weigh 1.5 processes
    assert files.get("memory.limit_in_bytes", files.get("memory.max")) == str(300 << 20)
    assert files["pids.max"] == "100"
    assert await master.call("bus_call", cid=4, service="/stringEchoService", request={"data": "still here"},
                             timeout=5) == {"data": "still here"}
    assert psutil.Process(echo).is_running() and psutil.Process(spin).is_running()
    # the new limit holds too: one busy loop never hits 1.5 cores (a CPU count, robust on a loaded machine)
    before = (await master.call("stats", cid=4))["cpu"]
    await asyncio.sleep(0.5)
    after = (await master.call("stats", cid=4))["cpu"]
    assert after["periods"] > before["periods"] and after["throttled"] == before["throttled"]
    # a limit the kernel refuses is an error naming it, and changes nothing else
    with pytest.raises(RCEError, match="memory"):
        await master.call("resize_container", cid=4, limits={"memory": 1})
    with pytest.raises(RCEError, match="pids"):
        await master.call("resize_container", cid=4, limits={"pids": -3})
    # 0 lifts a limit
    r = await master.call("resize_container", cid=4, limits={"cpu": 0})
    assert "cpu" not in r["limits"]
    files = (await master.call("stats", cid=4))["sandbox_info"]["cgroup"]["files"]
    assert files.get("cpu.shares", files.get("cpu.weight")) in ("1024", "100")   # back to one process's weight

    # Prometheus on the host, labelled by container and node
    port = cp.ready_info()["metrics_port"]
    text = await asyncio.to_thread(lambda: urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10)
                                   .read().decode())
    assert 'rce_container_cpu_percent{ctag="lim",user="u"}' in text
    assert 'rce_container_memory_limit_bytes{ctag="lim",user="u"} 3.145728e+08' in text
    assert 'rce_node_messages_out_total{ctag="lim",node="echo",user="u"} 3.0' in text
    assert 'rce_node_rss_bytes{ctag="lim",node="spin",user="u"}' in text
    assert "rce_environment_rss_bytes{" in text and "rce_container_host_containers 1.0" in text
    assert 'rce_container_tasks_limit{ctag="lim",user="u"} 100.0' in text


async def test_the_original_clients_size_is_not_a_task_limit(ns_rig):
    # rce-comm 20130902 always sends containerData {size: 1}: a size class, recorded; its nodes run
    master, _ = ns_rig
    assert (await create(master, 7, "orig", size=1))["sandbox"] == "namespaced"
    info = (await master.call("stats", cid=7))["sandbox_info"]
    assert info["cgroup"]["files"]["pids.max"] == "max"
    await add_node(master, 7, "echo", name="echo")
    await master.wait_bus(7, echo_ready("echo"))
    assert await master.call("bus_call", cid=7, service="/stringEchoService", request={"data": "size 1"},
                             timeout=5) == {"data": "size 1"}
    assert (await master.call("stats", cid=7))["limits"] == {"size": 1}


async def test_out_of_memory_kill_is_reported_and_respawned(ns_rig):
    master, _ = ns_rig
    await create(master, 5, "oom", memory=48)
    await add_node(master, 5, "hog", pkg="CTest", exe="hog.py", respawn={"delay": 0.1, "limit": 1})
    final = await master.wait_status(lambda s: s["ntag"] == "hog" and s["status"] == "exited", timeout=30)
    seq = [(s["status"], s.get("signal"), s.get("reason")) for s in master.statuses_of(5, "hog")]
    oom = "killed: out of memory (limit 48 MiB)"
    assert seq == [("started", None, None), ("respawning", 9, oom), ("started", None, None),
                   ("exited", 9, f"{oom}; respawn limit reached")], seq
    assert final["signal"] == 9
    s = await master.call("stats", cid=5)
    assert s["memory"]["oom_kills"] >= 2 and s["per_node"]["hog"]["last_exit"] == {"signal": 9, "reason": oom}


def _ns_holders(ns: tuple[set[str], float]) -> list[int]:
    """Pids of processes (anywhere on the host, zombies aside) in one of the namespaces of
    ``ns = (inodes, t)`` that were born before ``t`` (the kernel reuses a freed namespace's
    inode number at once: a container started later, by another test on this machine, may
    get it)."""
    inodes, t = ns
    out = []
    for p in psutil.pids():
        try:
            proc = psutil.Process(p)
            if proc.status() == psutil.STATUS_ZOMBIE or proc.create_time() > t:
                continue
        except psutil.NoSuchProcess:
            continue
        for kind in ("net", "pid", "mnt"):
            try:
                if os.readlink(f"/proc/{p}/ns/{kind}") in inodes:
                    out.append(p)
                    break
            except OSError:
                pass
    return out


async def _container_footprint(master, cid) -> tuple[list[int], list[Path], tuple[set[str], float], int]:
    """(pids in its cgroup, cgroup dirs, (namespace inodes, the latest birth of its processes), data port)."""
    s = await master.call("stats", cid=cid)
    info = s["sandbox_info"]
    dirs = [Path(d) for d in info["cgroup"]["dirs"]]
    pids = [int(p) for p in (dirs[0] / "cgroup.procs").read_text().split()]
    port = int(s["environment"]["data_addr"].rsplit(":", 1)[1])
    born = max(psutil.Process(p).create_time() for p in pids)     # psutil's clock, as _ns_holders compares
    return pids, dirs, (set(info["namespaces"].values()), born), port


def _port_closed(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


async def test_teardown_leaves_no_process_cgroup_namespace_or_port(ns_rig, tmp_path):
    master, cp = ns_rig
    await create(master, 6, "doomed", memory=256, pids=50)
    await add_node(master, 6, "echo", name="echo")
    stubborn = (await add_node(master, 6, "stubborn", pkg="CTest", exe="stubborn.py"))["pid"]  # ignores TERM, forks
    await master.wait_bus(6, echo_ready("echo"))
    await wait_stdout(master, 6, "stubborn")
    pids, dirs, ns, port = await _container_footprint(master, 6)
    assert len(pids) >= 6 and stubborn in pids and all(d.is_dir() for d in dirs) and _ns_holders(ns)
    await master.call("destroy_container", cid=6)
    assert not await wait_gone(pids, 5), "processes of a destroyed container are left"
    assert not [d for d in dirs if d.exists()], "cgroup directories of a destroyed container are left"
    assert not _ns_holders(ns), "something still lives in the destroyed container's namespaces"
    assert _port_closed(port), "the data port of the destroyed container's environment is still open"

    # a crashed environment: its init sees its stdin close, the kernel empties the namespace,
    # the task set removes the cgroup
    await create(master, 7, "fragile", memory=256)
    await add_node(master, 7, "stubborn", pkg="CTest", exe="stubborn.py")
    await wait_stdout(master, 7, "stubborn")
    pids, dirs, ns, port = await _container_footprint(master, 7)
    os.kill((await master.call("stats", cid=7))["environment"]["pid"], signal.SIGKILL)
    await master.wait_status(lambda s: s["cid"] == 7 and s["status"] == "exited")
    assert not await wait_gone(pids, 5)
    holders = _ns_holders(ns)
    assert not holders, [(p, psutil.Process(p).status(), psutil.Process(p).cmdline()) for p in holders]
    deadline = time.monotonic() + 5
    while any(d.exists() for d in dirs) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
    assert not [d for d in dirs if d.exists()]
    await master.call("destroy_container", cid=7)

    # host shutdown with containers running: the fixture's teardown checks processes and cgroups
    await create(master, 8, "left-running", cpu=1)
    await add_node(master, 8, "stubborn", pkg="CTest", exe="stubborn.py")
    await wait_stdout(master, 8, "stubborn")
    pids8, _, ns8, _ = await _container_footprint(master, 8)
    assert await cp.terminate() == 0
    assert not await wait_gone(pids8, 5)
    holders = _ns_holders(ns8)
    assert not holders, [(p, psutil.Process(p).status(), psutil.Process(p).cmdline()) for p in holders]


async def test_unconfined_fallback_says_so_and_works(tmp_path):
    master, cp = await start_host(tmp_path, "--sandbox", "unconfined")
    try:
        assert master.registration["sandbox"] == "unconfined"
        res = await create(master, 1, "plain", cpu=0.5, memory=64)
        assert res["sandbox"] == "unconfined"
        await add_node(master, 1, "echo", name="echo")
        await master.wait_bus(1, echo_ready("echo"))
        async with TcpServer() as srv:
            await add_node(master, 1, "probe", pkg="CTest", exe="probe.py", args=[str(srv.port)])
            seen = json.loads((await wait_stdout(master, 1, "probe"))[0])
        assert seen["tcp"] == "ok" and srv.accepted == 1            # no network namespace
        assert any("stringEcho" in cl for cl in seen["procs"].values())   # the host's processes
        s = await master.call("stats", cid=1)
        assert s["sandbox"] == "unconfined" and "cgroup" not in s["sandbox_info"]
        assert s["processes"] >= 1 and s["rss_mib"] > 0 and s["per_node"]["echo"]["rss_mib"] > 0
        r = await master.call("resize_container", cid=1, limits={"cpu": 2})   # recorded, not enforced
        assert r == {"sandbox": "unconfined", "limits": {"cpu": 2, "memory": 64}}
        assert await master.call("bus_call", cid=1, service="/stringEchoService", request={"data": "ok"},
                                 timeout=5) == {"data": "ok"}
        pid = (await master.call("stats", cid=1))["per_node"]["echo"]["pid"]
        assert await cp.terminate() == 0
        assert not await wait_gone([pid], 5)
    except BaseException:
        print(cp.log_text())
        raise
    finally:
        await stop_host(master, cp)


def test_a_starting_host_removes_the_cgroups_a_dead_host_left():
    assert os.geteuid() == 0, NEEDS_ROOT
    from rce_container import sandbox as sandboxes
    dead = psutil.Popen(["true"])
    dead.wait()                                          # a pid that no longer runs
    stale = sandboxes.host_scope("gc-test", dead.pid)
    layout = cgroups.host_layout(stale)
    left = cgroups.CgroupSet(layout, "c1")
    left.create()                                        # what a SIGKILLed task set leaves
    assert all(d.is_dir() for d in left.unique_dirs)
    mine = sandboxes.host_scope("gc-test")
    try:
        sandboxes.NamespaceSandbox.prepare_host(mine)
        assert not [d for d in left.unique_dirs if d.parent.exists()], "the dead task set's scope is still there"
    finally:
        sandboxes.NamespaceSandbox.cleanup_host(mine)
        cgroups.remove_tree([d.parent for d in left.unique_dirs])
