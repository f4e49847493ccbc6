"""rce_master.failover without sockets: lost containers re-created with their parameters,
interfaces, nodes and connections, against stand-in task set links that record what they are
told (:class:`test_core_master_requests.Link`)."""
from __future__ import annotations

import asyncio

import pytest

from rce.plumbing.errors import Unavailable
from rce.plumbing.tasks import Tasks
from rce_master.control import Control
from rce_master.failover import Failover
from rce_master.state.model import LIMIT_KEYS
from rce_master.requests import Request, handle
from rce_master.state.master_state import MasterState
from rce_master.state.store import MemoryStore
from test_core_master_requests import Link, notes

U = "alice"
ROBOT, HOST_A, HOST_B = 1, 2, 3
ROBOT_ADDR = "tcp://robots:10030"


class Cloud:
    """A state with a robot task set, hosts A and B (all linked), robot r1 connected, and a
    :class:`Failover` whose ``wait`` and ``stable`` the test may set."""

    def __init__(self, **failover) -> None:
        self.state = MasterState()
        self.state.register_taskset("robot", "re1", "robots", {"data_addr": ROBOT_ADDR})
        self.control = Control(self.state)
        self.robot = Link()
        self.control.peers[ROBOT] = self.robot
        self.hosts: dict[int, Link] = {}
        for name in ("A", "B"):
            self.add_host(name)
        self.state.robot_connect(U, "r1", ROBOT)
        self.tasks = Tasks("test")
        self.failover = Failover(self.state, self.control, self.tasks, **failover)

    def add_host(self, name: str) -> Link:
        ts = self.state.register_taskset("container", name, f"host{name}", {})
        link = self.hosts[ts.tid] = self.control.peers[ts.tid] = Link()
        link.answers["create_container"] = lambda a: {"data_addr": f"tcp://host{name}:{a['cid']}",
                                                      "sandbox": "unconfined"}
        return link

    async def ask(self, type_: str, data: dict) -> None:
        await handle(Request(U, "r1", self.state, self.control), type_, data)

    async def echo_container(self, ctag: str = "c1") -> None:
        """CC (it lands on host A: both are empty), a parameter, a node, two container-side
        interfaces connected to two robot-side ones."""
        await self.ask("CC", {"containerTag": ctag})
        await self.ask("CN", {
            "setParam": [{"containerTag": ctag, "name": "rate", "value": 10}],
            "addNodes": [{"containerTag": ctag, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
            "addInterfaces": [iface(ctag, "req", "PublisherInterface", "/stringEchoReq"),
                              iface(ctag, "resp", "SubscriberInterface", "/stringEchoResp"),
                              iface("r1", "req", "SubscriberConverter"), iface("r1", "resp", "PublisherConverter")]})
        await self.ask("CX", {"connect": [{"tagA": f"{ctag}/req", "tagB": "r1/req"},
                                          {"tagA": f"{ctag}/resp", "tagB": "r1/resp"}]})
        for link in (self.robot, *self.hosts.values()):
            link.sent.clear()

    def lose_host(self, tid: int):
        """Host ``tid``'s link closed: what the server does (drop it, then the failover)."""
        del self.control.peers[tid]
        lost, robots = self.state.drop_taskset(tid)
        return self.failover.taskset_lost(lost, robots)

    async def settled(self) -> None:
        """Wait until every re-creation task has ended."""
        while running := [r.task for r in self.failover.recoveries.values() if r.task and not r.task.done()]:
            await asyncio.wait(running)


def iface(etag: str, itag: str, itype: str, addr: str | None = None) -> dict:
    return {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": "std_msgs/String",
            **({"addr": addr} if addr else {})}


@pytest.fixture
async def cloud():
    c = Cloud()
    yield c
    await c.tasks.cancel_all()


async def test_host_lost_container_re_created_on_the_other_host_with_everything(cloud):
    await cloud.echo_container()
    c = cloud.state.containers[(U, "c1")]
    old_cid = c.cid
    await cloud.lose_host(HOST_A)
    # the robot-side ends were cut first (iu false), then the robot heard why
    assert [(op, a["iid"]) for op, a in cloud.robot.sent[:2]] == [("disconnect", 3), ("disconnect", 4)]
    assert notes(cloud.robot)[:2] == [("ST", {"topic": "container", "cTag": "c1", "status": "lost"}),
                                      ("ER", "container 'c1' was lost: its host went away; it is being re-created")]
    await cloud.settled()
    new_cid = c.cid
    assert (c.state, c.tid, c.data_addr) == ("running", HOST_B, f"tcp://hostB:{new_cid}") and new_cid > old_cid
    host_b = cloud.hosts[HOST_B]
    assert host_b.sent == [
        ("create_container", {"cid": new_cid, "user": U, "ctag": "c1", "group": None,
                              "limits": dict.fromkeys(LIMIT_KEYS), "deadline_ms": None, "handoff": False}),
        ("set_param", {"cid": new_cid, "name": "rate", "value": 10}),
        ("add_interface", {"cid": new_cid, "iid": 1, "tag": "c1/req", "itype": "PublisherInterface",
                           "cls": "std_msgs/String", "addr": "/stringEchoReq"}),
        ("add_interface", {"cid": new_cid, "iid": 2, "tag": "c1/resp", "itype": "SubscriberInterface",
                           "cls": "std_msgs/String", "addr": "/stringEchoResp"}),
        ("add_node", {"cid": new_cid, "ntag": "echo", "pkg": "Test", "exe": "stringEcho.py", "args": "",
                      "name": None, "namespace": None, "respawn": None}),
        ("connect", {"cid": new_cid, "iid": 1, "peer_iid": 3, "peer_addr": ROBOT_ADDR,
                     "peer_cls": "std_msgs/String", "token": cloud.control.key.connection_token(1, 3, ROBOT_ADDR)}),
        ("connect", {"cid": new_cid, "iid": 2, "peer_iid": 4, "peer_addr": ROBOT_ADDR,
                     "peer_cls": "std_msgs/String", "token": cloud.control.key.connection_token(2, 4, ROBOT_ADDR)})]
    # the robot-side ends get the new data address (iu true) and their credentials for it, then ST running
    assert [a for op, a in cloud.robot.sent if op == "connect"] == [
        {"iid": me, "peer_iid": peer, "peer_addr": c.data_addr, "peer_cls": "std_msgs/String",
         "token": cloud.control.key.connection_token(me, peer, c.data_addr)} for me, peer in ((3, 1), (4, 2))]
    assert notes(cloud.robot)[-1] == ("ST", {"topic": "container", "cTag": "c1", "status": "running",
                                             "sandbox": "unconfined"})
    assert len(cloud.state.connections) == 2 and cloud.state.nodes[(U, "c1", "echo")].status == "running"
    assert cloud.failover.recovered == 1 and cloud.state.tasksets[HOST_B].containers == 1


async def test_no_other_host_it_waits_and_a_host_that_registers_takes_it(cloud):
    await cloud.echo_container()
    await cloud.lose_host(HOST_B)                           # the empty one: nothing to do
    await cloud.lose_host(HOST_A)
    await asyncio.sleep(0)                                  # the task looks for a host and finds none
    c = cloud.state.containers[(U, "c1")]
    assert c.state == "lost"
    link = cloud.add_host("C")
    cloud.failover.host_registered()
    await cloud.settled()
    assert c.state == "running" and link.ops()[0] == "create_container" and c.data_addr.startswith("tcp://hostC:")


async def test_gives_up_after_wait_without_a_host():
    cloud = Cloud(wait=0.05)
    await cloud.echo_container()
    await cloud.lose_host(HOST_B)
    await cloud.lose_host(HOST_A)
    await cloud.settled()
    assert cloud.state.containers[(U, "c1")].state == "lost" and cloud.failover.gave_up == 1
    assert notes(cloud.robot)[-1][1].startswith("container 'c1' could not be re-created: no container host could "
                                                "take it within 0.05 s")
    await cloud.tasks.cancel_all()


async def test_failed_re_creations_are_undone_and_bounded():
    cloud = Cloud(attempts=2, wait=0.05)
    await cloud.echo_container()
    cloud.add_host("C")
    for tid in (HOST_B, 4):
        cloud.hosts[tid].answers["add_node"] = Unavailable("no such package")
    await cloud.lose_host(HOST_A)
    await cloud.settled()
    c = cloud.state.containers[(U, "c1")]
    assert c.state == "lost" and cloud.failover.gave_up == 1
    for tid in (HOST_B, 4):                                 # each host failed once, and was cleaned up
        ops = cloud.hosts[tid].ops()
        assert ops[0] == "create_container" and ops[-1] == "destroy_container"
        assert cloud.hosts[tid].sent[-1][1] == {"cid": cloud.hosts[tid].sent[0][1]["cid"]}
    assert notes(cloud.robot)[-1] == ("ER", "container 'c1' could not be re-created: 2 re-creations failed; "
                                            "it stays lost (DC it to give it up)")
    assert cloud.state.tasksets[HOST_B].containers == 0 and cloud.state.tasksets[4].containers == 0
    await cloud.tasks.cancel_all()


async def test_dc_while_it_is_re_created_forgets_it_and_the_new_host_is_cleaned(cloud):
    await cloud.echo_container()
    go_on = asyncio.Event()
    created = asyncio.Event()

    async def slow_create(a):
        if not created.is_set():                            # the re-creation's waits; the new CC's does not
            created.set()
            await go_on.wait()
        return {"data_addr": f"tcp://hostB:{a['cid']}", "sandbox": "unconfined"}
    host_b = cloud.hosts[HOST_B]
    host_b.request = _waiting(host_b, "create_container", slow_create)
    await cloud.lose_host(HOST_A)
    await created.wait()
    cid = cloud.state.containers[(U, "c1")].cid
    await cloud.ask("DC", {"containerTag": "c1"})           # at once, while its create runs
    assert (U, "c1") not in cloud.state.containers and cloud.state.connections == set()
    await cloud.ask("CC", {"containerTag": "c1"})           # the tag is free again
    go_on.set()
    await cloud.settled()
    assert ("destroy_container", {"cid": cid}) in host_b.sent
    assert cloud.state.containers[(U, "c1")].state == "running"
    assert not any(d.get("status") == "running" and op == "ST" for op, d in notes(cloud.robot)[:-1]
                   if isinstance(d, dict))


def _waiting(link: Link, op: str, answer):
    """``link.request`` answering ``op`` with coroutine function ``answer`` (others as before)."""
    plain = link.request

    async def request(op_: str, args: dict, timeout: float | None):
        if op_ != op:
            return await plain(op_, args, timeout)
        link.sent.append((op_, args))
        return await answer(args)
    return request


async def test_environment_lost_is_re_created_on_its_own_host(cloud):
    await cloud.echo_container()
    c = cloud.state.containers[(U, "c1")]
    await cloud.failover.environment_lost(HOST_B, c.cid, "its environment was killed by SIGKILL")   # not there
    await cloud.failover.environment_lost(HOST_A, c.cid + 100, "its environment was killed by SIGKILL")
    assert c.state == "running" and cloud.robot.sent == []
    assert cloud.hosts[HOST_B].sent == [("destroy_container", {"cid": c.cid})]             # only what is left there
    assert cloud.hosts[HOST_A].sent == [("destroy_container", {"cid": c.cid + 100})]
    cloud.hosts[HOST_A].sent.clear()
    cloud.hosts[HOST_B].sent.clear()
    old_cid = c.cid
    await cloud.failover.environment_lost(HOST_A, c.cid, "its environment was killed by SIGKILL")
    assert notes(cloud.robot)[:2] == [("ST", {"topic": "container", "cTag": "c1", "status": "lost"}),
                                      ("ER", "container 'c1' was lost: its environment was killed by SIGKILL; "
                                             "it is being re-created")]
    await cloud.settled()
    assert (c.state, c.tid) == ("running", HOST_A)          # its own host, though B is empty
    assert cloud.hosts[HOST_B].sent == []
    assert cloud.hosts[HOST_A].sent[0] == ("destroy_container", {"cid": old_cid})      # what is left of it there
    assert cloud.hosts[HOST_A].sent[1][0] == "create_container"


async def test_an_environment_that_keeps_dying_is_given_up():
    cloud = Cloud(attempts=2, stable=60)
    await cloud.echo_container()
    c = cloud.state.containers[(U, "c1")]
    for _ in range(2):
        await cloud.failover.environment_lost(HOST_A, c.cid, "its environment exited with code 1")
        await cloud.settled()
        assert c.state == "running"
    await cloud.failover.environment_lost(HOST_A, c.cid, "its environment exited with code 1")
    await cloud.settled()
    assert c.state == "lost" and cloud.failover.gave_up == 1 and cloud.failover.recovered == 2
    await cloud.tasks.cancel_all()


async def test_two_containers_connected_to_each_other_are_connected_once_both_run(cloud):
    await cloud.ask("CC", {"containerTag": "a"})
    await cloud.ask("CC", {"containerTag": "b", "containerData": {"group": "g"}})
    cloud.state.containers[(U, "b")].tid = HOST_A           # both on host A (placement put b on B)
    await cloud.ask("CN", {"addInterfaces": [iface("a", "out", "SubscriberInterface", "/x"),
                                             iface("b", "in", "PublisherInterface", "/y")]})
    await cloud.ask("CX", {"connect": [{"tagA": "a/out", "tagB": "b/in"}]})
    cloud.hosts[HOST_B].sent.clear()
    await cloud.lose_host(HOST_A)
    await cloud.settled()
    a, b = cloud.state.containers[(U, "a")], cloud.state.containers[(U, "b")]
    assert a.state == b.state == "running"
    connects = [x for op, x in cloud.hosts[HOST_B].sent if op == "connect"]
    assert sorted((x["iid"], x["peer_addr"]) for x in connects) == [(1, b.data_addr), (2, a.data_addr)]


async def test_a_new_master_re_creates_the_lost_containers_it_finds():
    cloud = Cloud()
    await cloud.echo_container()
    await cloud.lose_host(HOST_A)
    await cloud.tasks.cancel_all()                          # the master died while it re-created c1
    again = MasterState(MemoryStore(cloud.state.store.items()))
    again.mark_tasksets_absent()
    assert again.containers[(U, "c1")].state in ("lost", "recovering")
    control = Control(again)
    tasks = Tasks("test")
    failover = Failover(again, control, tasks)
    failover.resume()
    assert again.containers[(U, "c1")].state == "lost"
    await asyncio.sleep(0)
    link = Link()
    link.answers["create_container"] = {"data_addr": "tcp://back:1", "sandbox": "unconfined"}
    again.taskset_back(HOST_B, "B", "hostB", {})
    control.peers[HOST_B] = link
    failover.host_registered()
    while any(r.task and not r.task.done() for r in failover.recoveries.values()):
        await asyncio.wait([r.task for r in failover.recoveries.values()])
    assert again.containers[(U, "c1")].state == "running" and link.ops()[0] == "create_container"
    await tasks.cancel_all()
