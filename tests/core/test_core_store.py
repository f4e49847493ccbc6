"""rce_master.state.store and the master's state on it: every change is a record in the store, a
failed operation changes nothing, and the state rebuilt from the store's records equals the
original (what the next issue's restart from a SQLite or etcd store relies on)."""
from __future__ import annotations

import dataclasses
import math

import pytest

from rce.plumbing.errors import RequestError
from rce.protocol.schema import InterfaceComponent, NodeComponent
from rce_master.state.model import password_digest
from rce_master.state.master_state import MasterState
from rce_master.state.store import MemoryStore

U, V = "alice", "bob"


# -- the store -------------------------------------------------------------------------------------
def test_memory_store_put_get_delete_and_order():
    s = MemoryStore()
    s.commit([(("container", U, "c2"), {"cid": 2}), (("container", U, "c1"), {"cid": 1}),
              (("user", U), {"name": U})])
    assert s.get(("container", U, "c1")) == {"cid": 1} and s.get(("container", U, "nope")) is None
    assert [k for k, _ in s.items()] == [("container", U, "c1"), ("container", U, "c2"), ("user", U)]
    assert [k for k, _ in s.items("user")] == [("user", U)]
    s.commit([(("container", U, "c1"), None), (("container", U, "c2"), {"cid": 22})])   # delete, replace
    assert dict(s.items()) == {("container", U, "c2"): {"cid": 22}, ("user", U): {"name": U}}
    assert len(s) == 2


def test_memory_store_records_are_copies():
    s = MemoryStore()
    rec = {"data": {"cpu": 1}}
    s.commit([(("container", U, "c"), rec)])
    rec["data"]["cpu"] = 99
    got = s.get(("container", U, "c"))
    got["data"]["cpu"] = 7
    assert s.get(("container", U, "c")) == {"data": {"cpu": 1}}


@pytest.mark.parametrize("bad", [{"v": object()}, {"v": math.nan}, {"v": {1, 2}}])
def test_memory_store_batch_is_all_or_nothing(bad):
    s = MemoryStore([(("user", U), {"name": U})])
    with pytest.raises(RequestError, match="record param/alice/c/p is not JSON"):
        s.commit([(("user", U), None), (("param", U, "c", "p"), bad)])
    assert dict(s.items()) == {("user", U): {"name": U}}


def test_memory_store_copy():
    a = MemoryStore([(("user", U), {"name": U})])
    b = MemoryStore(a.items())
    b.commit([(("user", V), {"name": V})])
    assert len(a) == 1 and len(b) == 2


# -- the state on its store ----------------------------------------------------------------------------
def busy_state() -> MasterState:
    """Every kind of record: users, task sets (one lost), robots, containers (one lost, one
    resized), nodes with statuses, parameters, interfaces of both sides, connections."""
    s = MasterState()
    s.add_user(U, "pw")
    s.add_user(V, "pw2")
    s.register_taskset("robot", "re1", "hostA", {"data_addr": "tcp://10.0.0.1:10030", "ws_url": "ws://a/"})
    s.register_taskset("container", "ch1", "hostB", {"capacity": {"cpu": 4, "memory": 4096}})
    s.register_taskset("robot", "re2", "hostC", {})
    s.robot_connect(U, "r1", 1)
    s.robot_connect(V, "r1", 1)
    for user, ctag, data in ((U, "c1", {"cpu": 1.5, "memory": 256, "group": "g"}), (U, "c2", {"cpu": 0.5}),
                             (V, "c1", None)):
        c, _ = s.add_container(user, "r1", ctag, data)
        s.container_ready(c, f"unix:/{user}-{ctag}", "unconfined")
    s.add_container(U, "r1", "starting", None)
    s.resize(U, "c2", {"cpu": 2.0, "memory": 128})
    c, n = s.add_node(U, NodeComponent.model_validate({"containerTag": "c1", "nodeTag": "n1", "pkg": "Test",
                                                   "exe": "stringEcho.py"}))
    s.node_running(n)
    s.add_node(U, NodeComponent.model_validate({"containerTag": "c1", "nodeTag": "n2", "pkg": "Test", "exe": "x"}))
    s.node_status(c.cid, "n2", "exited", {"code": 1, "reason": "boom"})
    s.set_param(U, "c1", "/speed", 0.5)
    s.set_param(V, "c1", "cfg", {"a": [1, None, "x"]})
    for user, robot, etag, itag, itype in ((U, "r1", "c1", "pub", "PublisherInterface"),
                                           (U, "r1", "r1", "sub", "SubscriberConverter"),
                                           (U, "r1", "c2", "sub", "SubscriberInterface"),
                                           (V, "r1", "c1", "srv", "ServiceClientInterface")):
        s.add_interface(user, robot, InterfaceComponent.model_validate({"endpointTag": etag, "interfaceTag": itag,
                                                               "interfaceType": itype, "className": "std_msgs/String"}))
    s.connect(U, "c1/pub", "r1/sub")
    s.connect(U, "c1/pub", "c2/sub")
    assert s.drop_taskset(3) == ([], [])           # nothing on it: only the task set goes
    return s


def assert_same(a: MasterState, b: MasterState) -> None:
    assert a.snapshot() == b.snapshot()
    for table in ("users", "tasksets", "robots", "containers", "nodes", "params", "interfaces", "counters"):
        assert getattr(a, table) == getattr(b, table), table
    assert a.connections == b.connections
    for t in a.tasksets.values():                 # the derived load too
        u = b.tasksets[t.tid]
        assert (t.robots, t.containers, t.cpu_load, t.mem_load) == (u.robots, u.containers, u.cpu_load, u.mem_load)


def test_state_rebuilt_from_its_store_equals_the_original():
    s = busy_state()
    again = MasterState(MemoryStore(s.store.items()))
    assert_same(s, again)
    # users come back with their password check; the id counters go on where they were
    again.authenticate(U, password_digest("pw"))
    assert again.add_container(U, "r1", "next", None)[0].cid == s.add_container(U, "r1", "next", None)[0].cid
    assert again.register_taskset("robot", "x", "h", {}).tid == 4
    # the connection index works on the rebuilt state
    pairs, owned = again.robot_disconnect(U, "r1")
    assert [(a.tag, b.tag) for a, b in pairs] == [("c1/pub", "r1/sub")]
    assert again.connection_count(again.interface(U, "c1/pub").iid) == 1


def test_every_change_is_in_the_store():
    s = busy_state()
    kinds = {k[0] for k, _ in s.store.items()}
    assert kinds == {"user", "counter", "taskset", "robot", "container", "node", "param", "interface",
                     "connection"}
    assert s.store.get(("container", U, "c2"))["data"] == {"cpu": 2.0, "memory": 128}
    assert s.store.get(("node", U, "c1", "n2"))["detail"] == {"code": 1, "reason": "boom"}
    assert s.store.get(("param", U, "c1", "/speed"))["value"] == 0.5
    assert s.store.get(("taskset", "3")) is None
    # removing things removes their records
    s.robot_disconnect(U, "r1")
    s.remove_container(U, "c1")
    s.robot_disconnect(V, "r1")
    s.del_user(V)
    assert_same(s, MasterState(MemoryStore(s.store.items())))
    assert not [k for k, _ in s.store.items() if k[:3] == ("node", U, "c1") or k[:3] == ("param", U, "c1")]
    assert [k for k, _ in s.store.items("connection")] == []


def test_the_state_on_a_store_with_records_loads_them():
    store = MemoryStore()
    s = MasterState(store)
    s.add_user(U, "pw")
    s.register_taskset("container", "ch", "h", {})
    s.add_container(U, "r1", "c", {"memory": 100})
    assert_same(s, MasterState(store))


class FailingStore(MemoryStore):
    """A store whose commits fail (a full disk, a lost etcd quorum)."""
    fail = False

    def commit(self, changes):
        if self.fail:
            raise RequestError("the store refused the batch")
        super().commit(changes)


def test_a_failed_commit_leaves_state_and_store_as_they_were():
    store = FailingStore()
    s = MasterState(store)
    s.register_taskset("container", "ch", "h", {})
    s.robot_connect(U, "r1", 1)
    c, _ = s.add_container(U, "r1", "c1", {"cpu": 1})
    s.container_ready(c, "unix:/x", "")
    s.add_interface(U, "r1", InterfaceComponent.model_validate({"endpointTag": "c1", "interfaceTag": "i",
                                                       "interfaceType": "PublisherInterface",
                                                       "className": "std_msgs/String"}))
    before = dataclasses.replace(s.tasksets[1]), s.snapshot(), dict(store.items())
    store.fail = True
    for op in (lambda: s.add_container(U, "r1", "c2", {"cpu": 2}),
               lambda: s.remove_container(U, "c1"),
               lambda: s.drop_taskset(1),
               lambda: s.resize(U, "c1", {"cpu": 3}),
               lambda: s.robot_disconnect(U, "r1")):
        with pytest.raises(RequestError, match="refused the batch"):
            op()
        assert (s.tasksets[1], s.snapshot(), dict(store.items())) == before
        assert s.container(U, "c1") is c and c.state == "running" and s.counters == {"tid": 2, "cid": 2, "iid": 2}
    store.fail = False
    assert s.add_container(U, "r1", "c2", None)[0].cid == 2


def test_a_value_that_is_not_json_is_refused_before_anything_changes():
    s = MasterState()
    s.register_taskset("container", "ch", "h", {})
    c, _ = s.add_container(U, "r1", "c1", None)
    s.container_ready(c, "unix:/x", "")
    with pytest.raises(RequestError, match="not JSON"):
        s.set_param(U, "c1", "p", math.inf)
    assert s.params == {} and s.store.get(("param", U, "c1", "p")) is None


def test_changes_happen_only_inside_operations():
    s = MasterState()
    with pytest.raises(RuntimeError, match="inside an operation"):
        s._write(("user", U), {"name": U, "salt": "", "scrypt": ""})
