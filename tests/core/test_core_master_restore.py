"""The master's state after a restart, and the reconciliation with the task sets that come back
(rce_master.state.reconcile, docs/INTERNALS.md "Master state and restart"), sans I/O: the state rebuilt
from a reopened SQLite file equals the one before, ids go on, task sets are absent until they
re-register, and a returning task set's report decides what is kept, lost, forgotten or dropped."""
from __future__ import annotations

from pathlib import Path

import pytest

from rce.plumbing.errors import RequestError, Unavailable
from rce.protocol.schema import InterfaceComponent
from rce_master.state.reconcile import register
from rce_master.state.sqlite_store import SqliteStore
from rce_master.state.master_state import MasterState, TaskSetAbsent
from rce_master.state.store import MemoryStore
from test_core_store import FailingStore, assert_same, busy_state

U, V = "alice", "bob"
ECHO = {"pkg": "Test", "exe": "stringEcho.py"}


def restarted(s: MasterState) -> MasterState:
    """What a master started on ``s``'s records finds (its task sets absent)."""
    again = MasterState(MemoryStore(s.store.items()))
    again.mark_tasksets_absent()
    return again


# -- restore -------------------------------------------------------------------------------------------
def test_state_on_a_reopened_sqlite_file_equals_the_original_and_ids_go_on(tmp_path: Path):
    path = tmp_path / "master.sqlite3"
    with SqliteStore(path) as store:
        s = busy_state()
        store.commit(s.store.items())
        live = MasterState(store)                     # the master works on the file ...
        live.add_user("carol", "pw3")
        live.remove_container(U, "starting")
        before = live.snapshot()
        counters = dict(live.counters)
    with SqliteStore(path) as store:                  # ... dies, and a new one opens it
        again = MasterState(store)
        assert again.snapshot() == before
        assert_same(again, MasterState(MemoryStore(store.items())))
        # new ids never reuse old ones: counters go on, also for ids whose records are gone
        assert again.register_taskset("robot", "x", "h", {}).tid == counters["tid"]
        assert again.add_container(U, "r1", "new", None)[0].cid == counters["cid"]
        assert again.add_interface(U, "r1", InterfaceComponent.model_validate({
            "endpointTag": "r1", "interfaceTag": "new", "className": "a/B",
            "interfaceType": "PublisherConverter"})).iid == counters["iid"]
    with SqliteStore(path) as store:                  # and those changes were stored too
        assert MasterState(store).snapshot()["containers"][-1]["ctag"] == "new"


def test_task_sets_of_a_restored_state_are_absent_until_they_re_register():
    s = restarted(busy_state())
    assert [t["absent"] for t in s.snapshot()["tasksets"]] == [True, True]
    assert s.store.get(("taskset", "1"))["lost"] is True
    with pytest.raises(TaskSetAbsent, match="start rce-robot"):
        s.pick_robot_taskset()
    with pytest.raises(Unavailable, match="no container host"):
        s.pick_container_host({})
    assert [t.tid for t in s.absent_tasksets()] == [2, 1]          # container hosts first
    assert [t.tid for t in s.mark_tasksets_absent()] == [1, 2]       # again: nothing changes
    out = register(s, "robot", "re1", "hostA", {"tid": 1, "ws_url": "ws://a/", "robots": [{"user": U, "robot": "r1"},
                                                                                           {"user": V, "robot": "r1"}]})
    assert out.resumed and s.pick_robot_taskset().tid == 1 and [t.tid for t in s.absent_tasksets()] == [2]
    assert not s.tasksets[1].lost and s.tasksets[1].info == {"ws_url": "ws://a/"}     # the report is not info
    assert s.tasksets[1].robots == 2


def test_register_without_tid_is_a_new_task_set_as_before():
    s = restarted(busy_state())
    out = register(s, "container", "ch9", "h", {"capacity": {"cpu": 2}})
    assert out.answer() == {"tid": 4} and not out.resumed
    assert s.tasksets[4].info == {"capacity": {"cpu": 2}, "zone": "cloud"} and s.tasksets[2].lost


@pytest.mark.parametrize("args, error", [
    ({"tid": 2}, "task set 2 was a container task set, not a 'robot' one"),
    ({"tid": 0}, "tid must be a positive integer, got 0"),
    ({"tid": "1"}, "tid must be a positive integer"),
    ({"tid": 1, "robots": {"user": U}}, "robots must be a list, got dict"),
    ({"tid": 1, "robots": [{"user": U}]}, r"robots\[0\].robot must be a non-empty string, got None"),
    ({"tid": 1, "robots": ["r1"]}, r"robots\[0\] must be an object, got str"),
    ({"tid": 1, "interfaces": [3, True]}, r"interfaces\[1\] must be a positive integer, got True"),
])
def test_a_bad_robot_report_is_refused_naming_the_field_and_changes_nothing(args, error):
    s = restarted(busy_state())
    before = dict(s.store.items())
    with pytest.raises(RequestError, match=error):
        register(s, "robot", "re1", "hostA", args)
    assert dict(s.store.items()) == before


@pytest.mark.parametrize("args, error", [
    ({"tid": 2, "containers": [{"cid": 1}]}, r"containers\[0\].data_addr must be a non-empty string"),
    ({"tid": 2, "containers": [{"cid": -1, "data_addr": "x"}]}, r"containers\[0\].cid must be a positive integer"),
    ({"tid": 2, "containers": [{"cid": 1, "data_addr": "x", "nodes": [{"ntag": "n1"}]}]},
     r"containers\[0\].nodes\[0\].status must be a non-empty string"),
    ({"tid": 2, "containers": [{"cid": 1, "data_addr": "x", "nodes": [{"ntag": "n1", "status": "flying"}]}]},
     r"containers\[0\].nodes\[0\].status must be one of starting, running, started, respawning, exited, "
     r"got 'flying'"),
    ({"tid": 2, "containers": [{"cid": 1, "data_addr": "x", "nodes": "n1"}]}, r"containers\[0\].nodes must be a list"),
])
def test_a_bad_host_report_is_refused_naming_the_field(args, error):
    s = restarted(busy_state())
    with pytest.raises(RequestError, match=error):
        register(s, "container", "ch1", "hostB", args)
    assert s.tasksets[2].lost


def test_the_tid_of_a_registered_task_set_is_refused():
    s = restarted(busy_state())
    register(s, "robot", "re1", "hostA", {"tid": 1})
    with pytest.raises(RequestError, match="task set 1 is registered already"):
        register(s, "robot", "re1-again", "hostA", {"tid": 1})


# -- a robot task set comes back -------------------------------------------------------------------------
def test_robot_task_set_keeps_reported_robots_forgets_the_others_and_closes_unknown_ones():
    s = restarted(busy_state())
    iids = {i.tag: i.iid for i in s.interfaces.values() if i.user == U}
    out = register(s, "robot", "re1", "hostA", {
        "tid": 1, "robots": [{"user": U, "robot": "r1"}, {"user": U, "robot": "ghost"}],
        "interfaces": [iids["r1/sub"], 99]})
    assert [(r.user, r.robot) for r in out.kept] == [(U, "r1")]
    assert [(r.user, r.robot) for r in out.gone] == [(V, "r1")]        # not reported: the shell forgets it
    assert out.answer() == {"tid": 1, "resumed": True, "drop_containers": [], "drop_nodes": [],
                            "drop_interfaces": [99], "close_robots": [{"user": U, "robot": "ghost"}]}
    assert out.pairs == [] and (U, "r1") in s.robots


def test_robot_task_set_without_an_interface_forgets_it_with_its_connections():
    s = restarted(busy_state())
    out = register(s, "robot", "re1", "hostA", {"tid": 1, "robots": [{"user": U, "robot": "r1"}],
                                                "interfaces": []})
    assert [(a.tag, b.tag) for a, b in out.pairs] == [("c1/pub", "r1/sub")]
    assert (U, "r1", "sub") not in s.interfaces and s.connection_count(s.interface(U, "c1/pub").iid) == 1
    assert s.store.get(("interface", U, "r1", "sub")) is None


def test_robot_task_set_with_an_unknown_tid_registers_anew_and_closes_its_robots():
    s = restarted(busy_state())
    out = register(s, "robot", "re7", "hostA", {"tid": 77, "robots": [{"user": U, "robot": "r1"}],
                                                "interfaces": [5]})
    assert out.taskset.tid == 4 and not out.resumed               # a fresh id, never the one it sent
    assert out.answer() == {"tid": 4, "resumed": False, "drop_containers": [], "drop_nodes": [],
                            "drop_interfaces": [5], "close_robots": [{"user": U, "robot": "r1"}]}
    assert s.robots[(U, "r1")].tid == 1 and s.tasksets[1].lost     # its namesake on tid 1 waits for tid 1


# -- a container host comes back ------------------------------------------------------------------------
def host_report(s: MasterState, **changes) -> dict:
    """The containers of host 2 as a host reports them (``changes``: ctag -> entry or None to leave out)."""
    out = []
    for c in sorted(s.containers.values(), key=lambda c: c.cid):
        entry = {"cid": c.cid, "data_addr": c.data_addr or "tcp://h:1",
                 "nodes": [{"ntag": n.ntag, "status": n.status} for n in s.nodes.values() if n.ctag == c.ctag
                           and n.user == c.user]}
        entry = changes.get(f"{c.user}/{c.ctag}", entry)
        if entry is not None:
            out.append(entry)
    return {"tid": 2, "containers": out}


def test_host_keeps_reported_containers_and_loses_the_others():
    s = restarted(busy_state())
    report = host_report(s, **{f"{U}/c2": None, f"{U}/starting": None})
    out = register(s, "container", "ch1", "hostB", report)
    assert out.resumed and out.answer()["drop_containers"] == []
    assert [c.ctag for c in out.lost] == ["c2", "starting"]
    states = {(c.user, c.ctag): c.state for c in s.containers.values()}
    assert states == {(U, "c1"): "running", (U, "c2"): "lost", (V, "c1"): "running", (U, "starting"): "lost"}
    assert s.store.get(("container", U, "c2"))["state"] == "lost"
    assert s.tasksets[2].containers == 2                            # the lost ones weigh on no host
    assert s.pick_container_host({}).tid == 2


def test_host_moves_a_container_to_its_new_address_and_tid():
    s = restarted(busy_state())
    c1 = s.containers[(U, "c1")]
    report = host_report(s, **{f"{U}/c1": {"cid": c1.cid, "data_addr": "tcp://new:2", "sandbox": "namespaced"}})
    report["tid"] = 55                                             # unknown: a new task set adopts them
    out = register(s, "container", "ch1b", "hostB", report)
    new = out.taskset.tid
    assert out.readdressed == [c1] and (c1.tid, c1.data_addr, c1.sandbox) == (new, "tcp://new:2", "namespaced")
    assert s.tasksets[new].containers == 4 and s.tasksets[2].containers == 0
    assert s.store.get(("container", U, "c1"))["tid"] == new
    # the old host comes back too late: what the new one has is not its any more
    back = register(s, "container", "ch1", "hostB", host_report(s))
    assert back.answer()["drop_containers"] == sorted(c.cid for c in s.containers.values())
    assert back.lost == [] and all(c.tid == new for c in s.containers.values())


def test_host_reports_unknown_and_lost_containers_to_drop():
    s = restarted(busy_state())
    s.container_lost(s.containers[(V, "c1")])
    lost_cid = s.containers[(V, "c1")].cid
    report = host_report(s)
    report["containers"].append({"cid": 999, "data_addr": "tcp://h:9"})
    out = register(s, "container", "ch1", "hostB", report)
    assert out.answer()["drop_containers"] == [lost_cid, 999]
    assert s.containers[(V, "c1")].state == "lost" and out.lost == []


def test_host_reconciles_nodes():
    s = restarted(busy_state())
    c1 = s.containers[(U, "c1")]
    report = host_report(s, **{f"{U}/c1": {"cid": c1.cid, "data_addr": c1.data_addr,
                                            "nodes": [{"ntag": "n1", "status": "respawning"},
                                                      {"ntag": "stray", "status": "running"}]}})
    out = register(s, "container", "ch1", "hostB", report)
    assert s.nodes[(U, "c1", "n1")].status == "respawning"
    assert (U, "c1", "n2") not in s.nodes and s.store.get(("node", U, "c1", "n2")) is None
    assert [(c.ctag, ntag) for c, ntag in out.nodes_lost] == [("c1", "n2")]
    assert out.answer()["drop_nodes"] == [{"cid": c1.cid, "ntag": "stray"}]
    assert out.readdressed == []


def test_host_without_nodes_in_its_report_keeps_the_stored_nodes():
    s = restarted(busy_state())
    c1 = s.containers[(U, "c1")]
    out = register(s, "container", "ch1", "hostB", host_report(s, **{f"{U}/c1": {"cid": c1.cid,
                                                                                   "data_addr": c1.data_addr}}))
    assert {k for k in s.nodes if k[:2] == (U, "c1")} == {(U, "c1", "n1"), (U, "c1", "n2")}
    assert out.nodes_lost == []


def test_reconciliation_is_one_batch_a_failed_store_changes_nothing():
    s = busy_state()
    store = FailingStore(s.store.items())
    again = MasterState(store)
    again.mark_tasksets_absent()
    before = again.snapshot(), dict(store.items())
    store.fail = True
    with pytest.raises(RequestError, match="refused the batch"):
        register(again, "container", "ch1", "hostB", host_report(again, **{f"{U}/c2": None}))
    assert (again.snapshot(), dict(store.items())) == before
    assert again.containers[(U, "c2")].state == "running" and again.tasksets[2].lost


def test_grace_over_drops_absent_task_sets_hosts_first():
    s = restarted(busy_state())
    register(s, "robot", "re1", "hostA", {"tid": 1, "robots": [{"user": U, "robot": "r1"},
                                                                {"user": V, "robot": "r1"}]})
    for ts in s.absent_tasksets():
        lost, robots = s.drop_taskset(ts.tid)
        assert sorted(c.ctag for c in lost) == ["c1", "c1", "c2", "starting"] and robots == []
    assert {c.state for c in s.containers.values()} == {"lost"} and list(s.tasksets) == [1]
    assert_same(s, MasterState(MemoryStore(s.store.items())))
