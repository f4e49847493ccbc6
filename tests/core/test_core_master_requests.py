"""rce_master.requests and rce_master.control without sockets: the request handlers against
stand-in task set links that record what they are told and answer, refuse or time out as the
test says. A refused step is undone in the state; a timed-out one on the far end too."""
from __future__ import annotations

from typing import Any

import pytest

from rce.plumbing.errors import NotFound, ProtocolError, RequestError, Timeout, Unavailable
from rce_master.control import Control
from rce_master.state.model import LIMIT_KEYS
from rce_master.requests import CN_STEPS, CX_STEPS, REQUESTS, Request, handle
from rce_master.state.master_state import MasterState

U = "alice"
ROBOT_TID, HOST_TID = 1, 2


class Link:
    """A task set's control link: records ``(op, args)``; ``answers[op]`` is a result, an
    exception to raise, or a function of the args returning either."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, dict]] = []
        self.answers: dict[str, Any] = {}

    async def request(self, op: str, args: dict, timeout: float | None) -> Any:
        self.sent.append((op, args))
        answer = self.answers.get(op, {})
        if callable(answer):
            answer = answer(args)
        if isinstance(answer, BaseException):
            raise answer
        return answer

    def notify(self, op: str, **args: Any) -> None:
        self.sent.append((op, args))

    def ops(self) -> list[str]:
        return [op for op, _ in self.sent]


@pytest.fixture
def world():
    """A state with a robot task set and a container host (both linked), robot r1 connected."""
    state = MasterState()
    state.register_taskset("robot", "re1", "hostA", {"data_addr": "tcp://10.0.0.1:10030"})
    state.register_taskset("container", "ch1", "hostB", {})
    control = Control(state)
    robot_link, host_link = Link(), Link()
    control.peers.update({ROBOT_TID: robot_link, HOST_TID: host_link})
    host_link.answers["create_container"] = lambda a: {"data_addr": f"unix:/{a['ctag']}", "sandbox": "unconfined"}
    state.robot_connect(U, "r1", ROBOT_TID)
    return state, control, robot_link, host_link


def req(world, robot: str = "r1") -> Request:
    return Request(U, robot, world[0], world[1])


def notes(link: Link) -> list:
    return [(a["type"], a["data"]) for op, a in link.sent if op == "notify"]


def test_the_tables():
    assert set(REQUESTS) == {"CC", "DC", "CN", "CX"}
    assert list(CN_STEPS.steps) == ["addNodes", "removeNodes", "setParam", "deleteParam", "addInterfaces",
                                    "removeInterfaces", "resizeContainer"]
    assert list(CX_STEPS.steps) == ["connect", "disconnect"]


async def test_unknown_request_type(world):
    with pytest.raises(RequestError, match="unknown request type 'XX'"):
        await handle(req(world), "XX", {})


async def test_the_data_is_parsed_into_its_model_before_any_step(world):
    """The master reads a request through its schema model: data the schema refuses changes nothing
    and tells no task set, even in a list whose other items are good."""
    state, _, robot_link, host_link = world
    good = {"containerTag": "c1", "nodeTag": "n", "pkg": "Test", "exe": "e"}
    with pytest.raises(ProtocolError, match=r"CN.data.addNodes\[1\]: missing key 'pkg'"):
        await handle(req(world), "CN", {"addNodes": [good, {"containerTag": "c1", "nodeTag": "m", "exe": "e"}]})
    with pytest.raises(ProtocolError, match="unknown interface type 'PublisherThing'"):
        await handle(req(world), "CN", {"addInterfaces": [{"endpointTag": "r1", "interfaceTag": "i",
                                                           "interfaceType": "PublisherThing", "className": "a/B"}]})
    assert state.nodes == {} and state.interfaces == {} and host_link.sent == robot_link.sent == []


# -- CC / DC ---------------------------------------------------------------------------------------------
async def test_create_container(world):
    state, _, robot_link, host_link = world
    await handle(req(world), "CC", {"containerTag": "c1", "containerData": {"cpu": 1, "group": "g"}})
    c = state.container(U, "c1")
    assert (c.state, c.data_addr, c.sandbox, c.group) == ("running", "unix:/c1", "unconfined", "g")
    assert host_link.sent == [("create_container", {"cid": c.cid, "user": U, "ctag": "c1", "group": "g",
                                                    "limits": {**dict.fromkeys(LIMIT_KEYS), "cpu": 1},
                                                    "deadline_ms": None, "handoff": False})]
    assert notes(robot_link) == [("ST", {"topic": "container", "cTag": "c1", "status": "running",
                                         "sandbox": "unconfined"})]


async def test_create_container_refused_by_its_host_is_forgotten(world):
    state, _, robot_link, host_link = world
    host_link.answers["create_container"] = RequestError("no room")
    with pytest.raises(RequestError, match="no room"):
        await handle(req(world), "CC", {"containerTag": "c1"})
    assert state.containers == {} and state.tasksets[HOST_TID].containers == 0
    assert host_link.ops() == ["create_container"] and notes(robot_link) == []


async def test_create_container_timed_out_is_destroyed_on_its_host_too(world):
    state, _, _, host_link = world
    host_link.answers["create_container"] = Timeout("ch1 did not answer 'create_container' within 60 s")
    with pytest.raises(Timeout):
        await handle(req(world), "CC", {"containerTag": "c1"})
    assert state.containers == {}
    assert host_link.ops() == ["create_container", "destroy_container"]
    assert host_link.sent[1][1] == {"cid": host_link.sent[0][1]["cid"]}


async def test_container_removed_while_created_is_destroyed(world):
    state, _, _, host_link = world

    def created_but_gone(a):
        state.remove_container(U, a["ctag"])           # e.g. its robot left meanwhile
        return {"data_addr": "unix:/x"}
    host_link.answers["create_container"] = created_but_gone
    with pytest.raises(Unavailable, match="removed or lost while it was created"):
        await handle(req(world), "CC", {"containerTag": "c1"})
    assert state.containers == {} and host_link.ops() == ["create_container", "destroy_container"]


async def test_destroy_container(world):
    state, _, _, host_link = world
    await handle(req(world), "CC", {"containerTag": "c1"})
    cid = state.container(U, "c1").cid
    await handle(req(world), "DC", {"containerTag": "c1"})
    assert state.containers == {} and host_link.sent[-1] == ("destroy_container", {"cid": cid})
    with pytest.raises(NotFound, match="'c1'"):
        await handle(req(world), "DC", {"containerTag": "c1"})


# -- CN ---------------------------------------------------------------------------------------------------
@pytest.fixture
async def running(world):
    await handle(req(world), "CC", {"containerTag": "c1"})
    world[3].sent.clear()
    world[2].sent.clear()
    return world


def node(ntag: str) -> dict:
    return {"containerTag": "c1", "nodeTag": ntag, "pkg": "Test", "exe": "stringEcho.py"}


async def test_add_nodes_one_refused(running):
    state, _, _, host_link = running
    host_link.answers["add_node"] = lambda a: RequestError(f"no exe for {a['ntag']}") if a["ntag"] == "bad" else {}
    with pytest.raises(RequestError) as ei:
        await handle(req(running), "CN", {"addNodes": [node("good"), node("bad")]})
    assert ei.value.message == "no exe for bad"
    assert set(state.nodes) == {(U, "c1", "good")} and state.nodes[(U, "c1", "good")].status == "running"
    assert host_link.ops() == ["add_node", "add_node"]


async def test_add_node_timed_out_is_removed_on_the_host_too(running):
    state, _, _, host_link = running
    host_link.answers["add_node"] = Timeout("slow")
    with pytest.raises(RequestError, match="slow"):
        await handle(req(running), "CN", {"addNodes": [node("n")]})
    assert state.nodes == {} and host_link.sent[-1] == ("remove_node", {"cid": 1, "ntag": "n"})


async def test_node_status_before_the_launch_answer_is_kept(running):
    state, _, _, host_link = running

    def exits_at_once(a):
        state.node_status(1, a["ntag"], "exited", {"code": 3})
        return {}
    host_link.answers["add_node"] = exits_at_once
    await handle(req(running), "CN", {"addNodes": [node("n")]})
    assert state.nodes[(U, "c1", "n")].status == "exited"


async def test_params_and_resize(running):
    state, _, _, host_link = running
    host_link.answers["resize_container"] = lambda a: {"limits": a["limits"]}
    await handle(req(running), "CN", {"setParam": [{"containerTag": "c1", "name": "p", "value": [1, 2]}],
                                      "resizeContainer": [{"containerTag": "c1", "cpu": 2, "memory": 64}]})
    assert state.params == {(U, "c1", "p"): [1, 2]}
    assert state.container(U, "c1").data == {"cpu": 2, "memory": 64}
    assert (state.tasksets[HOST_TID].cpu_load, state.tasksets[HOST_TID].mem_load) == (2.0, 64.0)
    host_link.answers["set_param"] = RequestError("bus refused")
    with pytest.raises(RequestError, match="bus refused"):
        await handle(req(running), "CN", {"setParam": [{"containerTag": "c1", "name": "q", "value": 1}]})
    assert (U, "c1", "q") not in state.params                  # recorded only once the bus has it
    await handle(req(running), "CN", {"deleteParam": [{"containerTag": "c1", "name": "p"}]})
    assert state.params == {} and host_link.sent[-1] == ("delete_param", {"cid": 1, "name": "p"})
    assert [op for op in host_link.ops()] == ["set_param", "resize_container", "set_param", "delete_param"]


def iface(etag: str, itag: str, itype: str) -> dict:
    return {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": "std_msgs/String"}


async def test_add_interfaces_refused_or_timed_out(running):
    state, _, robot_link, host_link = running
    robot_link.answers["add_interface"] = RequestError("endpoint refused")
    host_link.answers["add_interface"] = Timeout("host slow")
    with pytest.raises(RequestError) as ei:
        await handle(req(running), "CN", {"addInterfaces": [iface("r1", "a", "SubscriberConverter"),
                                                            iface("c1", "b", "PublisherInterface")]})
    assert ei.value.message == "endpoint refused; host slow"
    assert state.interfaces == {}
    assert robot_link.ops() == ["add_interface"]                          # refused: nothing to take back
    assert host_link.ops() == ["add_interface", "remove_interface"]      # timed out: taken back
    assert host_link.sent[-1][1] == {"cid": 1, "iid": 2}


# -- CX ---------------------------------------------------------------------------------------------------
@pytest.fixture
async def interfaces(running):
    await handle(req(running), "CN", {"addInterfaces": [iface("r1", "a", "SubscriberConverter"),
                                                        iface("c1", "b", "PublisherInterface")]})
    running[2].sent.clear()
    running[3].sent.clear()
    return running


async def test_connect_and_disconnect(interfaces):
    state, control, robot_link, host_link = interfaces
    await handle(req(interfaces), "CX", {"connect": [{"tagA": "c1/b", "tagB": "r1/a"}]})
    assert len(state.connections) == 1
    # the receiving end (the PublisherInterface) first; each end gets its credential for sending to the other
    assert host_link.sent == [("connect", {"cid": 1, "iid": 2, "peer_iid": 1, "peer_addr": "tcp://10.0.0.1:10030",
                                           "peer_cls": "std_msgs/String",
                                           "token": control.key.connection_token(2, 1, "tcp://10.0.0.1:10030")})]
    assert robot_link.sent == [("connect", {"iid": 1, "peer_iid": 2, "peer_addr": "unix:/c1",
                                            "peer_cls": "std_msgs/String",
                                            "token": control.key.connection_token(1, 2, "unix:/c1")})]
    await handle(req(interfaces), "CX", {"disconnect": [{"tagA": "r1/a", "tagB": "c1/b"}]})
    assert state.connections == set() and robot_link.ops()[-1] == "disconnect" and host_link.ops()[-1] == "disconnect"


async def test_connect_refused_by_one_end_is_undone_on_both(interfaces):
    state, _, robot_link, host_link = interfaces
    robot_link.answers["connect"] = Unavailable("endpoint gone")
    with pytest.raises(RequestError, match="endpoint gone"):
        await handle(req(interfaces), "CX", {"connect": [{"tagA": "c1/b", "tagB": "r1/a"}]})
    assert state.connections == set()
    assert host_link.ops() == ["connect", "disconnect"] and robot_link.ops() == ["connect", "disconnect"]


async def test_remove_interface_tells_its_peers(interfaces):
    state, _, robot_link, host_link = interfaces
    await handle(req(interfaces), "CX", {"connect": [{"tagA": "c1/b", "tagB": "r1/a"}]})
    await handle(req(interfaces), "CN", {"removeInterfaces": [{"endpointTag": "c1", "interfaceTag": "b"}]})
    assert list(state.interfaces) == [(U, "r1", "a")] and state.connections == set()
    assert robot_link.sent[-1] == ("disconnect", {"iid": 1, "peer_iid": 2})
    assert host_link.sent[-1] == ("remove_interface", {"cid": 1, "iid": 2})


# -- teardowns --------------------------------------------------------------------------------------------
async def test_robot_gone_destroys_what_it_owns(interfaces):
    state, control, robot_link, host_link = interfaces
    await handle(req(interfaces), "CX", {"connect": [{"tagA": "c1/b", "tagB": "r1/a"}]})
    await control.robot_gone(U, "r1")
    assert (state.robots, state.containers, state.interfaces, state.connections) == ({}, {}, {}, set())
    assert host_link.ops()[-2:] == ["disconnect", "destroy_container"]


async def test_a_lost_container_can_always_be_destroyed_and_its_tag_created_again(interfaces):
    """Its host went away: DC forgets it at once (with its interfaces and connections, no call to
    the gone host), CC of the tag is refused with a clear answer until then, and works after."""
    state, control, robot_link, host_link = interfaces
    await handle(req(interfaces), "CX", {"connect": [{"tagA": "c1/b", "tagB": "r1/a"}]})
    del control.peers[HOST_TID]
    lost, _ = state.drop_taskset(HOST_TID)
    assert [c.ctag for c in lost] == ["c1"] and state.containers[(U, "c1")].state == "lost"
    assert len(state.connections) == 1                        # kept: its re-creation connects it again
    with pytest.raises(RequestError, match="lost with its host and waits for a container host"):
        await handle(req(interfaces), "CN", {"addNodes": [node("n")]})
    with pytest.raises(RequestError, match="c1.*lost with its host.*DC it first to create it afresh"):
        await handle(req(interfaces), "CC", {"containerTag": "c1"})
    robot_link.sent.clear()
    await handle(req(interfaces), "DC", {"containerTag": "c1"})
    assert state.containers == {} and state.connections == set() and list(state.interfaces) == [(U, "r1", "a")]
    assert robot_link.sent == [("disconnect", {"iid": 1, "peer_iid": 2})]
    assert host_link.ops() == ["connect"]                      # nothing more went to the gone host
    state.register_taskset("container", "ch2", "hostC", {})
    control.peers[3] = host_link
    await handle(req(interfaces), "CC", {"containerTag": "c1"})
    assert state.container(U, "c1").state == "running"


async def test_cc_of_a_tag_being_re_created_gets_a_clear_answer(running):
    state, _, _, _ = running
    c = state.container(U, "c1")
    state.container_lost(c)
    state.container_recovering(c, HOST_TID)
    with pytest.raises(RequestError, match="being re-created on another host; DC it first"):
        await handle(req(running), "CC", {"containerTag": "c1"})
    with pytest.raises(RequestError, match="being re-created.*once it runs \\(ST status running\\), or DC it"):
        await handle(req(running), "CN", {"setParam": [{"containerTag": "c1", "name": "p", "value": 1}]})
