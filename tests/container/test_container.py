"""The container task set as real processes: ``rce-container`` registered with an in-test
master, environments, nodes of the ``Test`` package, container-side interfaces wired over the
data plane to a robot-side data plane in the test process."""
from __future__ import annotations

import asyncio
import os
import shutil
import signal

import psutil
import pytest

from rce.transport.dataplane import DataPlane
from rce.plumbing.errors import MessageError, NotFound, ProtocolError, RequestError, Unavailable
from rce.messages import default_registry
from rce.node.package_path import load_package_types
from rce_container import sandbox as sandboxes

from .harness import (STEP, ContainerProcess, FakeMaster, RobotInterface, gone, has_service, kill_leftovers,
                      make_helper_package, topic, wait_gone)

pytestmark = pytest.mark.timeout(90)

STRING = "std_msgs/msg/String"
SANDBOX = sandboxes.select("auto").kind     # "namespaced" as root (CI), else "unconfined"


@pytest.fixture
def registry():
    reg = default_registry()
    load_package_types(reg)
    return reg


@pytest.fixture
async def rig(tmp_path):
    """(master, container process): a registered rce-container with the helper package on
    RCE_PACKAGE_PATH. Teardown: SIGTERM must exit 0 and leave no node process behind."""
    master = FakeMaster()
    await master.start()
    pkgs = make_helper_package(tmp_path / "pkgs")
    cp = ContainerProcess(tmp_path, master, {"RCE_PACKAGE_PATH": str(pkgs), "RCE_TEST_VAR": "v a l"})
    try:
        await cp.start()
        yield master, cp
        pids = [s["pid"] for s in master.statuses if s.get("pid")]
        code = await cp.terminate()
        assert code == 0, cp.log_text()
        alive = await wait_gone(pids, 5)
        kill_leftovers(alive)
        assert not alive, f"node processes survived shutdown: {alive}"
        assert not cp.runtime_dir.exists() or not any(cp.runtime_dir.iterdir()), list(cp.runtime_dir.iterdir())
    except BaseException:
        print(cp.log_text())
        raise
    finally:
        await cp.kill()
        await master.close()
        shutil.rmtree(cp.runtime_dir, ignore_errors=True)


async def create(master: FakeMaster, cid: int, ctag: str, group: str | None = None, user: str = "u") -> dict:
    return await master.call("create_container", cid=cid, user=user, ctag=ctag, group=group,
                             limits={"cpu": None, "memory": None, "size": None, "bandwidth": None})


async def add_node(master: FakeMaster, cid: int, ntag: str, pkg: str = "Test", exe: str = "stringEcho.py",
                   **kw) -> dict:
    return await master.call("add_node", cid=cid, ntag=ntag, pkg=pkg, exe=exe, args=kw.pop("args", ""),
                             name=kw.pop("name", None), namespace=kw.pop("namespace", None),
                             respawn=kw.pop("respawn", None))


def echo_ready(name: str, ns: str = ""):
    """describe() condition: the stringEcho node ``name`` in namespace ``ns`` is subscribed,
    publishes and serves its service (its names are relative: they resolve in ``ns``)."""
    node = f"{ns}/{name}"
    return lambda d: (node in topic(d, f"{ns}/stringEchoReq")["subscribers"]
                      and node in topic(d, f"{ns}/stringEchoResp")["publishers"]
                      and has_service(d, f"{ns}/stringEchoService"))


async def test_register_echo_and_service_over_the_data_plane(rig, registry):
    master, cp = rig
    reg = master.registration
    assert reg["kind"] == "container" and reg["name"] == "test-host" and reg["host"] == "127.0.0.1"
    assert reg["sandbox"] == SANDBOX
    assert reg["capacity"]["cpu"] >= 1 and reg["capacity"]["memory"] > 0

    res = await create(master, 1, "cTag_01")
    assert res["sandbox"] == SANDBOX and res["data_addr"].startswith("127.0.0.1:")
    print(f"container start (create_container -> environment ready): {res['startup_ms']} ms")
    assert cp.ready_info() == {"tid": 7, "pid": cp.proc.pid, "metrics_port": None, "sandbox": SANDBOX}
    assert await create(master, 1, "cTag_01") == res          # a replayed request is idempotent

    started = await add_node(master, 1, "strEcho", name="stringEcho")
    assert started["pid"] > 0
    st = await master.wait_status(lambda s: s["ntag"] == "strEcho" and s["status"] == "started")
    assert st["cid"] == 1 and st["pid"] == started["pid"]

    r = await master.call("add_interface", cid=1, iid=1, tag="cTag_01/stringEchoReq", itype="PublisherInterface",
                          cls="std_msgs/String", addr=None)
    assert r["addr"] == "/stringEchoReq"                     # default addr: "/" + iTag
    await master.call("add_interface", cid=1, iid=2, tag="cTag_01/stringEchoResp", itype="SubscriberInterface",
                      cls="std_msgs/String", addr="stringEchoResp")
    # the legacy RCE alpha name of ServiceClientInterface
    await master.call("add_interface", cid=1, iid=3, tag="cTag_01/srv", itype="ServiceInterface",
                      cls="Test/StringEcho", addr="/stringEchoService")
    d = await master.wait_bus(1, echo_ready("stringEcho"))
    assert "interface:cTag_01/stringEchoReq" in topic(d, "/stringEchoReq")["publishers"]
    assert "interface:cTag_01/stringEchoResp" in topic(d, "/stringEchoResp")["subscribers"]
    assert [n["name"] for n in d["nodes"]] == ["/stringEcho"]
    assert d["launched"][0]["pid"] == started["pid"] and d["launched"][0]["running"]

    plane = DataPlane("robot")
    await plane.listen("127.0.0.1", 0)
    plane.data_key = master.key.data_key(plane.addr)
    try:
        to_cloud = RobotInterface(plane, 101, "r1/req", "Subscriber", "std_msgs/String")
        from_cloud = RobotInterface(plane, 102, "r1/resp", "Publisher", "std_msgs/String")
        svc = RobotInterface(plane, 103, "r1/srv", "ServiceProvider", "Test/StringEcho")
        for iface, peer in ((to_cloud, 1), (from_cloud, 2), (svc, 3)):
            await iface.start()
            iface.connect(peer, res["data_addr"], bytes.fromhex(master.token(iface.iid, peer, res["data_addr"])))
            await master.call("connect", cid=1, iid=peer, peer_iid=iface.iid, peer_addr=plane.addr,
                              token=master.token(peer, iface.iid, plane.addr))

        for text in ("hello", "wörld " * 100):
            to_cloud.send_message(registry.json_to_bytes(STRING, {"data": text}))
            got = await asyncio.wait_for(from_cloud.inbox.get(), STEP)
            assert registry.bytes_to_json(STRING, got) == {"data": text}

        req_t, resp_t = registry.srv_types("Test/StringEcho")
        resp = await svc.call_peer(registry.json_to_bytes(req_t, {"data": "ping 42"}))
        assert registry.bytes_to_json(resp_t, resp) == {"data": "ping 42"}

        stats = await master.call("stats", cid=1)
        by_iid = {i["iid"]: i for i in stats["interfaces"]}
        assert by_iid[1]["msgs_in"] == 2 and by_iid[2]["msgs_out"] == 2 and by_iid[3]["msgs_in"] == 1
        assert by_iid[1]["bytes_in"] == by_iid[2]["bytes_out"] > 600
        assert stats["msgs_in"] == 3 and stats["dropped"] == {"interfaces": 0, "bus": 0}
        assert stats["nodes"] == {"count": 1, "running": 1, "starts": 1, "forked": 1, "restarts": 0}
        # the service call crosses the environment's data plane; a topic message takes the node's
        # direct link once its route is up (rce_container/direct_routes.py), the interfaces count both
        assert 1 <= stats["environment"]["dataplane"]["msgs_in"] <= 3
        host_stats = await master.call("stats")
        assert host_stats["tid"] == 7 and [c["cid"] for c in host_stats["containers"]] == [1]

        # admin tools on the bus: publish/sample and call with JSON
        sample = asyncio.create_task(master.call("bus_sample", cid=1, topic="/stringEchoResp", count=1, timeout=10))
        await master.wait_bus(1, lambda d: "admin:bus_sample" in topic(d, "/stringEchoResp")["subscribers"])
        pub = await master.call("bus_publish", cid=1, topic="stringEchoReq", type="std_msgs/String",
                                msg={"data": "from admin"})
        assert pub == {"delivered": 1}
        assert await sample == [{"data": "from admin"}]
        # ... and the robot saw it too, through the SubscriberInterface
        got = await asyncio.wait_for(from_cloud.inbox.get(), STEP)
        assert registry.bytes_to_json(STRING, got) == {"data": "from admin"}
        assert await master.call("bus_call", cid=1, service="/stringEchoService", request={"data": "x"},
                                 timeout=5) == {"data": "x"}

        # disconnect: the robot stops receiving; remove_interface drops the bus registration
        await master.call("disconnect", cid=1, iid=2, peer_iid=102)
        await master.call("remove_interface", cid=1, iid=1)
        d = await master.call("describe", cid=1)
        assert "interface:cTag_01/stringEchoReq" not in topic(d, "/stringEchoReq")["publishers"]
        with pytest.raises(NotFound):
            await master.call("connect", cid=1, iid=1, peer_iid=101, peer_addr=plane.addr)
    finally:
        await plane.close()


async def test_parameters(rig):
    master, _ = rig
    await create(master, 2, "params")
    await add_node(master, 2, "paramTest", exe="paramTest.py")
    for name, value in (("int", 99), ("str", "hello"), ("float", 3.5), ("bool", True)):
        await master.call("set_param", cid=2, name=name, value=value)
    await master.call("set_param", cid=2, name="tree", value={"a": 1, "b": {"c": [1, 2]}})
    await master.wait_bus(2, lambda d: has_service(d, "/parameterTest"))
    resp = await master.call("bus_call", cid=2, service="parameterTest", request={}, timeout=5)
    assert resp["msg"].splitlines() == ["int:   99", "str:   hello", "float: 3.5", "bool:  True"]
    d = await master.call("describe", cid=2)
    assert {"/int", "/str", "/float", "/bool", "/tree/a", "/tree/b/c"} <= set(d["params"])
    await master.call("delete_param", cid=2, name="int")
    resp = await master.call("bus_call", cid=2, service="parameterTest", request={}, timeout=5)
    assert resp["msg"].splitlines()[0] == "int:   <not set>"
    with pytest.raises(NotFound):
        await master.call("delete_param", cid=2, name="int")
    resized = await master.call("resize_container", cid=2, limits={"cpu": 2, "memory": None})
    assert resized["sandbox"] == SANDBOX and resized["limits"] == {"cpu": 2}


async def test_group_shares_one_bus_and_others_do_not_see_it(rig):
    master, _ = rig
    a, b, c = await asyncio.gather(create(master, 10, "A", group="g"), create(master, 11, "B", group="g"),
                                   create(master, 12, "C"))
    assert a["data_addr"] == b["data_addr"] != c["data_addr"]      # one environment per group
    # same group name of another user: a different environment
    other = await create(master, 13, "A", group="g", user="someone-else")
    assert other["data_addr"] not in (a["data_addr"], c["data_addr"])

    await add_node(master, 11, "echoB")
    await add_node(master, 12, "echoC")
    await master.wait_bus(10, echo_ready("echoB"))                  # B's node, seen from A
    await master.wait_bus(12, echo_ready("echoC"))
    d_a = await master.call("describe", cid=10)
    assert [n["name"] for n in d_a["nodes"]] == ["/echoB"] and d_a["launched"] == []
    d_c = await master.call("describe", cid=12)
    assert [n["name"] for n in d_c["nodes"]] == ["/echoC"]

    # A publishes; B's node echoes it (seen on A's side); C's node does not see it.
    on_a = asyncio.create_task(master.call("bus_sample", cid=10, topic="/stringEchoResp", count=1, timeout=10))
    on_c = asyncio.create_task(master.call("bus_sample", cid=12, topic="/stringEchoResp", count=1, timeout=1.5))
    await master.wait_bus(10, lambda d: "admin:bus_sample" in topic(d, "/stringEchoResp")["subscribers"])
    await master.wait_bus(12, lambda d: "admin:bus_sample" in topic(d, "/stringEchoResp")["subscribers"])
    assert await master.call("bus_publish", cid=10, topic="/stringEchoReq", type="std_msgs/String",
                             msg={"data": "group hello"}) == {"delivered": 1}
    assert await on_a == [{"data": "group hello"}]
    assert await on_c == []
    # C's own node works, so its silence above means something
    on_c = asyncio.create_task(master.call("bus_sample", cid=12, topic="/stringEchoResp", count=1, timeout=10))
    await master.wait_bus(12, lambda d: "admin:bus_sample" in topic(d, "/stringEchoResp")["subscribers"])
    await master.call("bus_publish", cid=12, topic="/stringEchoReq", type="std_msgs/String", msg={"data": "c"})
    assert await on_c == [{"data": "c"}]

    # parameters are per group
    await master.call("set_param", cid=10, name="shared", value=1)
    assert "/shared" in (await master.call("describe", cid=11))["params"]
    assert "/shared" not in (await master.call("describe", cid=12))["params"]

    # destroying B kills its node but keeps the group's environment for A
    pid_b = next(s["pid"] for s in master.statuses if s["ntag"] == "echoB" and s["status"] == "started")
    await master.call("destroy_container", cid=11)
    assert gone(pid_b)
    d_a = await master.call("describe", cid=10)
    assert d_a["nodes"] == [] and "/shared" in d_a["params"]
    with pytest.raises(NotFound):
        await master.call("describe", cid=11)


async def test_refusals_name_what_was_wrong(rig):
    master, _ = rig
    await create(master, 3, "errs")
    with pytest.raises(NotFound) as e:
        await add_node(master, 3, "n1", pkg="NoSuchPkg", exe="talker.py")
    assert "NoSuchPkg" in str(e.value) and "talker.py" in str(e.value)
    with pytest.raises(NotFound) as e:
        await add_node(master, 3, "n2", pkg="Test", exe="noSuchExe.py")
    assert "Test" in str(e.value) and "noSuchExe.py" in str(e.value)
    with pytest.raises(RequestError) as e:
        await add_node(master, 3, "n3", respawn={"delay": -1})
    assert "respawn" in str(e.value)

    with pytest.raises(MessageError) as e:
        await master.call("add_interface", cid=3, iid=30, tag="errs/x", itype="PublisherInterface",
                          cls="std_msgs/NoSuchMsg", addr=None)
    assert "std_msgs/NoSuchMsg" in str(e.value)
    with pytest.raises(MessageError) as e:        # a message class where a service class is needed
        await master.call("add_interface", cid=3, iid=31, tag="errs/y", itype="ServiceClientInterface",
                          cls="std_msgs/String", addr=None)
    assert "std_msgs/String" in str(e.value)
    with pytest.raises(RequestError) as e:
        await master.call("add_interface", cid=3, iid=32, tag="errs/z", itype="PublisherConverter",
                          cls="std_msgs/String", addr=None)
    assert "PublisherConverter" in str(e.value)
    with pytest.raises(ProtocolError) as e:
        await master.call("add_interface", cid=3, iid=33, tag="errs/w", itype="Teleporter", cls="std_msgs/String")
    assert "Teleporter" in str(e.value)
    with pytest.raises(NotFound) as e:
        await master.call("set_param", cid=999, name="x", value=1)
    assert "999" in str(e.value)
    with pytest.raises(NotFound):
        await master.call("bus_call", cid=3, service="/nobody", request={}, timeout=1)
    with pytest.raises(RequestError):
        await create(master, 3, "another-tag")         # a cid is not reused for another container
    # nothing above disturbed the container
    assert (await master.call("describe", cid=3))["launched"] == []


async def test_exit_codes_respawn_args_and_logs(rig):
    master, cp = rig
    await create(master, 4, "nodes")
    pkg_dir = cp.env["RCE_PACKAGE_PATH"] + "/CTest"
    # $(env X) reads the node's own environment, never a host variable (no leak of the host's secrets)
    with pytest.raises(RequestError, match="RCE_TEST_VAR"):
        await add_node(master, 4, "leak", pkg="CTest", exe="exiter.py", args="$(env RCE_TEST_VAR)")
    await add_node(master, 4, "once", pkg="CTest", exe="exiter.py",
                   args="3 $(find CTest)/x '$(env RCE_CONTAINER) $(optenv ROS_IP v a l)'")
    st = await master.wait_status(lambda s: s["ntag"] == "once" and s["status"] == "exited")
    assert st["code"] == 3 and "signal" not in st and st["cid"] == 4
    logs = await master.call("logs", cid=4, ntag="once")
    assert logs["stdout"] == [f"argv=3|{pkg_dir}/x|nodes v a l"] and logs["stderr"] == ["bye"]

    await add_node(master, 4, "shell", pkg="CTest", exe="run.sh", args=["a b", "$(optenv NOPE dflt)"])
    await master.wait_status(lambda s: s["ntag"] == "shell" and s["status"] == "exited")
    assert (await master.call("logs", cid=4, ntag="shell"))["stdout"] == ["shell-node a b dflt nodes"]

    await add_node(master, 4, "again", pkg="CTest", exe="exiter.py", args="4", respawn={"delay": 0.05, "limit": 2})
    final = await master.wait_status(lambda s: s["ntag"] == "again" and s["status"] == "exited")
    seq = [(s["status"], s.get("code"), s.get("restarts")) for s in master.statuses_of(4, "again")]
    assert seq == [("started", None, None), ("respawning", 4, 1), ("started", None, None),
                   ("respawning", 4, 2), ("started", None, None), ("exited", 4, None)]
    assert final["reason"] == "respawn limit reached"
    pids = [s["pid"] for s in master.statuses_of(4, "again") if s["status"] == "started"]
    assert len(set(pids)) == 3 and all(gone(p) for p in pids)
    assert len((await master.call("logs", cid=4, ntag="again"))["stdout"]) == 3   # output kept across restarts
    stats = await master.call("stats", cid=4)
    assert stats["nodes"]["restarts"] == 2 and stats["nodes"]["running"] == 0

    # name and namespace place the node; remove_node of a running node: SIGTERM (an rce.node
    # program exits 0 on it), reported as exited
    await add_node(master, 4, "echo", name="nsEcho", namespace="robot1")
    pid = (await master.wait_status(lambda s: s["ntag"] == "echo" and s["status"] == "started"))["pid"]
    await master.wait_bus(4, echo_ready("nsEcho", "/robot1"))
    await master.call("remove_node", cid=4, ntag="echo")
    assert gone(pid)
    st = await master.wait_status(lambda s: s["ntag"] == "echo" and s["status"] == "exited")
    assert st["code"] == 0 and st["reason"] == "removed"
    with pytest.raises(NotFound):
        await master.call("remove_node", cid=4, ntag="echo")


async def test_destroy_container_kills_every_node_process(rig):
    master, cp = rig
    await create(master, 5, "doomed")
    echo = (await add_node(master, 5, "echo"))["pid"]
    stubborn = (await add_node(master, 5, "stubborn", pkg="CTest", exe="stubborn.py"))["pid"]
    await master.wait_bus(5, echo_ready("echo"))
    # wait until the stubborn node ignores SIGTERM and has forked its grandchild
    deadline = asyncio.get_running_loop().time() + STEP
    while not (await master.call("logs", cid=5, ntag="stubborn"))["stdout"]:
        assert asyncio.get_running_loop().time() < deadline, "stubborn node never started"
        await asyncio.sleep(0.02)
    # the child's pid as the host sees it (in a PID namespace the node prints its own view)
    grandchild = next(p.pid for p in psutil.Process(stubborn).children(recursive=True) if p.name() == "sleep")
    socket_path = cp.runtime_dir / "c5" / "bus.sock"
    assert socket_path.exists()
    env_pid = (await master.call("stats", cid=5))["environment"]["pid"]

    await master.call("destroy_container", cid=5)       # SIGTERM, 1 s grace, then SIGKILL the groups
    assert gone(echo) and gone(stubborn)
    assert not await wait_gone([grandchild], 5), "a node's child survived destroy_container"
    assert not socket_path.exists() and not (cp.runtime_dir / "c5").exists()
    assert not await wait_gone([env_pid], 5), "the environment of the last container kept running"
    assert not any(s["status"] == "exited" for s in master.statuses_of(5, "echo"))  # no noise for a destroy
    with pytest.raises(NotFound):
        await master.call("destroy_container", cid=5)


async def test_master_loss_keeps_everything_and_the_host_re_registers(tmp_path):
    """The master goes away: the containers and nodes keep running and the host re-registers with
    its tid and a report; it destroys what the master's answer drops (docs/INTERNALS.md)."""
    master = FakeMaster()
    await master.start()
    cp = ContainerProcess(tmp_path, master)
    try:
        await cp.start()
        res = await create(master, 6, "orphan")
        pid = (await add_node(master, 6, "echo"))["pid"]
        await master.wait_status(lambda s: s["cid"] == 6 and s["status"] == "started")
        await master.wait_bus(6, echo_ready("echo"))
        master.registered.clear()
        await master.peer.close()                              # the master goes away, and comes back
        await asyncio.wait_for(master.registered.wait(), STEP)
        assert master.registration["tid"] == 7 and master.registration["containers"] == [
            {"cid": 6, "data_addr": res["data_addr"], "sandbox": res["sandbox"],
             "nodes": [{"ntag": "echo", "status": "started"}]}]
        assert cp.proc.returncode is None and not gone(pid)
        assert (await master.call("describe", cid=6))["topics"]     # the same environment serves it
        master.answer = {"tid": 7, "resumed": True, "drop_containers": [6], "drop_nodes": [], "drop_interfaces": [],
                         "close_robots": []}
        master.registered.clear()
        await master.peer.close()                              # back again, without container 6
        await asyncio.wait_for(master.registered.wait(), STEP)
        assert not await wait_gone([pid], STEP)
        for _ in range(int(STEP / 0.02)):                     # poll until the destroy is done (a condition)
            if not (cp.runtime_dir / "c6").exists():
                break
            await asyncio.sleep(0.02)
        assert not (cp.runtime_dir / "c6").exists()
        with pytest.raises(NotFound):
            await master.call("describe", cid=6)
        assert cp.proc.returncode is None
        assert "the master does not have this container" in cp.log_text()
    except BaseException:
        print(cp.log_text())
        raise
    finally:
        await cp.kill()
        await master.close()
        shutil.rmtree(cp.runtime_dir, ignore_errors=True)


async def test_environment_crash_is_reported_and_cleaned_up(rig):
    master, _ = rig
    await create(master, 7, "fragile")
    pid = (await add_node(master, 7, "stubborn", pkg="CTest", exe="stubborn.py"))["pid"]
    env_pid = (await master.call("stats", cid=7))["environment"]["pid"]
    os.kill(env_pid, signal.SIGKILL)
    st = await master.wait_status(lambda s: s["ntag"] == "stubborn" and s["status"] == "exited")
    assert st["cid"] == 7 and "environment exited" in st["reason"]
    assert not await wait_gone([pid], 5), "the task set did not kill the nodes of a crashed environment"
    with pytest.raises(Unavailable) as e:
        await master.call("describe", cid=7)
    assert "fragile" in str(e.value)
    await master.call("destroy_container", cid=7)
    # the host serves new containers after the crash
    assert (await create(master, 8, "fresh"))["sandbox"] == SANDBOX
