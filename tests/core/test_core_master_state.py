"""rce_master.state.master_state: the master's command data structure and its rules, sans I/O."""
from __future__ import annotations

import hashlib
import json

import pytest

from rce.plumbing.errors import AuthError, NotFound, RCEError, RequestError, Unavailable
from rce.protocol.schema import validate
from rce.contract.environment import NodeStatus
from rce_master.state.lifecycle import LIFECYCLES, NODE_TRANSITIONS, ContainerState, IllegalMove, check_move
from rce_master.state.model import User, password_digest
from rce_master.state.master_state import MasterState
from rce_master.state.store import MemoryStore

U, V = "alice", "bob"


@pytest.fixture
def ms() -> MasterState:
    """State with one robot task set (tid 1) and one container host (tid 2) without capacity limits."""
    s = MasterState()
    s.register_taskset("robot", "re1", "hostA", {"data_addr": "tcp://10.0.0.1:10030", "ws_url": "ws://hostA:9010/"})
    s.register_taskset("container", "ch1", "hostB", {"sandbox": "process-group"})
    return s


def running(ms: MasterState, user: str, ctag: str, owner: str = "r1", data: dict | None = None):
    c, _ = ms.add_container(user, owner, ctag, data)
    ms.container_ready(c, f"unix:/tmp/{user}-{ctag}.sock", "process-group")
    return c


def iface(ms: MasterState, user: str, robot: str, etag: str, itag: str, itype: str,
          cls: str = "std_msgs/String", addr: str | None = None):
    spec = {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": cls}
    if addr:
        spec["addr"] = addr
    return ms.add_interface(user, robot, component("addInterfaces", spec))


def component(key: str, spec: dict):
    """The model of CN component ``spec`` of list ``key``, as the master's request handlers get it
    (the schema refuses what is not a valid component, e.g. an unknown interface type)."""
    return getattr(validate({"type": "CN", "data": {key: [spec]}})[1], key)[0]


# -- users --------------------------------------------------------------------------------------
def test_password_digest_is_hex_sha256():
    assert password_digest("testUser") == hashlib.sha256(b"testUser").hexdigest()
    assert len(password_digest("")) == 64


def test_authenticate_with_digest():
    s = MasterState()
    s.add_user(U, "s3cret")
    s.authenticate(U, password_digest("s3cret"))
    s.authenticate(U, password_digest("s3cret").upper())         # hex is case-insensitive


@pytest.mark.parametrize("user, password", [
    (U, password_digest("wrong")),
    (U, "s3cret"),                                   # the clear password is not the digest
    (U, ""),
    (U, password_digest("s3cret")[:-1]),
    ("mallory", password_digest("s3cret")),          # unknown user
    ("", password_digest("s3cret")),
])
def test_authenticate_refused(user, password):
    s = MasterState()
    s.add_user(U, "s3cret")
    with pytest.raises(AuthError) as ei:
        s.authenticate(user, password)
    assert ei.value.code == "auth" and repr(user) in ei.value.message


@pytest.mark.parametrize("password", [None, 5])
def test_authenticate_non_string_password_is_an_auth_error(password):
    s = MasterState()
    s.add_user(U, "s3cret")
    with pytest.raises(AuthError):
        s.authenticate(U, password)


def test_stored_record_has_no_clear_password():
    u = User.create(U, "s3cret")
    rec = u.to_record()
    assert set(rec) == {"name", "salt", "scrypt", "role"}
    text = json.dumps(rec)
    assert "s3cret" not in text and password_digest("s3cret") not in text
    assert len(bytes.fromhex(rec["salt"])) == 16 and len(bytes.fromhex(rec["scrypt"])) == 32
    # scrypt of the digest, with the salt
    assert bytes.fromhex(rec["scrypt"]) == hashlib.scrypt(password_digest("s3cret").encode(),
                                                          salt=bytes.fromhex(rec["salt"]), n=2**14, r=8, p=1, dklen=32)
    back = User.from_record(rec)
    assert back.check(password_digest("s3cret")) and not back.check(password_digest("other"))


def test_same_password_different_salt():
    a, b = User.create("a", "pw"), User.create("b", "pw")
    assert a.salt != b.salt and a.key != b.key


@pytest.mark.parametrize("name, password, what", [
    ("", "pw", "illegal user name"),
    ("a b", "pw", "illegal user name"),
    ("a/b", "pw", "illegal user name"),
    ("ok_name-1.x", "", "password"),
])
def test_add_user_refused(name, password, what):
    s = MasterState()
    with pytest.raises(RequestError) as ei:
        s.add_user(name, password)
    assert what in ei.value.message
    assert s.users == {}


def test_add_user_duplicate_and_delete():
    s = MasterState()
    s.add_user(U, "pw")
    with pytest.raises(RequestError, match="already exists"):
        s.add_user(U, "other")
    s.authenticate(U, password_digest("pw"))                 # the first one stays
    s.del_user(U)
    with pytest.raises(NotFound):
        s.del_user(U)
    with pytest.raises(AuthError):
        s.authenticate(U, password_digest("pw"))


def test_del_user_with_connected_robot_refused(ms):
    ms.users[U] = User(U, b"s" * 16, b"k" * 32)
    ms.robot_connect(U, "r1", 1)
    with pytest.raises(RequestError, match="connected robots"):
        ms.del_user(U)
    ms.robot_disconnect(U, "r1")
    ms.del_user(U)
    assert U not in ms.users


# -- task sets and placement --------------------------------------------------------------------
def test_register_taskset():
    s = MasterState()
    a = s.register_taskset("robot", "a", "h", {})
    b = s.register_taskset("container", "b", "h", {})
    assert (a.tid, b.tid) == (1, 2) and s.tasksets[2] is b
    with pytest.raises(RequestError, match="unknown task set kind 'x'"):
        s.register_taskset("x", "c", "h", {})
    assert len(s.tasksets) == 2


def test_pick_robot_taskset_least_loaded():
    s = MasterState()
    with pytest.raises(Unavailable, match="rce-robot"):
        s.pick_robot_taskset()
    s.register_taskset("container", "c", "h", {})
    with pytest.raises(Unavailable):
        s.pick_robot_taskset()
    a = s.register_taskset("robot", "a", "h", {})
    b = s.register_taskset("robot", "b", "h", {})
    assert s.pick_robot_taskset() is a                          # tie: lowest tid
    s.robot_connect(U, "r1", a.tid)
    assert s.pick_robot_taskset() is b
    s.robot_connect(U, "r2", b.tid)
    s.robot_connect(U, "r3", b.tid)
    assert s.pick_robot_taskset() is a
    a.lost = True
    assert s.pick_robot_taskset() is b


def test_pick_container_host_none():
    s = MasterState()
    s.register_taskset("robot", "a", "h", {})
    with pytest.raises(Unavailable) as ei:
        s.pick_container_host({"cpu": 1, "memory": 100})
    assert "rce-container" in ei.value.message and "cpu 1" in ei.value.message


def test_pick_container_host_counts_containers_without_capacity():
    s = MasterState()
    h1 = s.register_taskset("container", "h1", "h", {})
    h2 = s.register_taskset("container", "h2", "h", {})
    assert s.pick_container_host({}) is h1
    s.add_container(U, "r", "c1", None)
    assert s.pick_container_host({}) is h2
    s.add_container(U, "r", "c2", None)
    assert s.pick_container_host({}) is h1


def test_pick_container_host_by_cpu_relative_to_capacity():
    s = MasterState()
    big = s.register_taskset("container", "big", "h", {"capacity": {"cpu": 8, "memory": 8192}})
    small = s.register_taskset("container", "small", "h", {"capacity": {"cpu": 2, "memory": 8192}})
    big.cpu_load = 2.0
    # big: (2 + 1) / 8 = 0.375; small: (0 + 1) / 2 = 0.5
    assert s.pick_container_host({"cpu": 1}) is big
    # the request itself counts: small (0 + 0.25) / 2 = 0.125 < big (2.25 / 8 = 0.28)
    assert s.pick_container_host({"cpu": 0.25}) is small


def test_pick_container_host_by_memory():
    s = MasterState()
    h1 = s.register_taskset("container", "h1", "h", {"capacity": {"cpu": 4, "memory": 1000}})
    h2 = s.register_taskset("container", "h2", "h", {"capacity": {"cpu": 4, "memory": 4000}})
    h1.mem_load = 100
    h2.mem_load = 1000
    # h1: (100 + 300) / 1000 = 0.4; h2: (1000 + 300) / 4000 = 0.325
    assert s.pick_container_host({"memory": 300}) is h2
    assert s.pick_container_host({"memory": 0}) is h1             # 0.1 vs 0.25


def test_pick_container_host_skips_hosts_without_room_and_lost_hosts():
    s = MasterState()
    h1 = s.register_taskset("container", "h1", "h", {"capacity": {"memory": 1000}})
    h2 = s.register_taskset("container", "h2", "h", {"capacity": {"memory": 500}})
    assert s.pick_container_host({"memory": 600}) is h1             # does not fit h2
    assert s.pick_container_host({"memory": 1000}) is h1            # exactly fits
    with pytest.raises(Unavailable, match="memory 1001"):
        s.pick_container_host({"memory": 1001})
    h1.lost = True
    with pytest.raises(Unavailable):
        s.pick_container_host({"memory": 600})
    assert s.pick_container_host({"memory": 100}) is h2


def test_pick_container_host_excluding_and_preferring():
    s = MasterState()
    h1 = s.register_taskset("container", "h1", "h", {})
    h2 = s.register_taskset("container", "h2", "h", {})
    s.add_container(U, "r", "c1", {})                               # h1 now holds one
    assert s.pick_container_host({}) is h2
    assert s.pick_container_host({}, prefer=h1.tid) is h1           # its own host, though busier
    assert s.pick_container_host({}, exclude={h2.tid}, prefer=h2.tid) is h1
    with pytest.raises(Unavailable):
        s.pick_container_host({}, exclude={h1.tid, h2.tid})


def test_pick_container_host_memory_capacity_is_checked_against_current_load():
    s = MasterState()
    s.register_taskset("container", "h1", "h", {"capacity": {"memory": 1000}})
    s.add_container(U, "r", "c1", {"memory": 700})
    with pytest.raises(Unavailable):
        s.add_container(U, "r", "c2", {"memory": 400})
    assert (U, "c2") not in s.containers
    s.add_container(U, "r", "c3", {"memory": 300})


# -- robots and containers ----------------------------------------------------------------------
def test_robot_connect_and_duplicate(ms):
    r = ms.robot_connect(U, "r1", 1)
    assert (r.user, r.robot, r.tid) == (U, "r1", 1) and ms.tasksets[1].robots == 1
    with pytest.raises(RequestError, match="already connected"):
        ms.robot_connect(U, "r1", 1)
    assert ms.tasksets[1].robots == 1
    ms.robot_connect(V, "r1", 1)                                    # robot IDs are per user
    assert ms.tasksets[1].robots == 2


def test_robot_id_and_container_tag_clash(ms):
    ms.add_container(U, "r1", "shared", None)
    with pytest.raises(RequestError, match="container tag"):
        ms.robot_connect(U, "shared", 1)
    ms.robot_connect(V, "shared", 1)                                # another user: fine
    ms.robot_connect(U, "r1", 1)
    with pytest.raises(RequestError, match="robot ID"):
        ms.add_container(U, "r1", "r1", None)
    assert (U, "r1") not in ms.containers


def test_add_container_accounting(ms):
    host = ms.tasksets[2]
    c, h = ms.add_container(U, "r1", "c1", {"cpu": 1.5, "memory": 256, "group": "g"})
    assert h is host and c.tid == 2 and c.state == "starting" and c.group == "g" and c.owner == "r1"
    c2, _ = ms.add_container(U, "r1", "c2", {"cpu": 0.5, "group": ""})
    assert c2.group is None and c2.cid == c.cid + 1
    assert (host.containers, host.cpu_load, host.mem_load) == (2, 2.0, 256.0)
    with pytest.raises(RequestError, match="already exists"):
        ms.add_container(U, "r1", "c1", None)
    assert host.containers == 2
    ms.remove_container(U, "c1")
    assert (host.containers, host.cpu_load, host.mem_load) == (1, 0.5, 0.0)
    ms.remove_container(U, "c2")
    assert (host.containers, host.cpu_load, host.mem_load) == (0, 0.0, 0.0)


def test_add_container_copies_its_data(ms):
    data = {"cpu": 1}
    c, _ = ms.add_container(U, "r1", "c1", data)
    data["cpu"] = 99
    ms.remove_container(U, "c1")
    assert ms.tasksets[2].cpu_load == 0.0 and c.data == {"cpu": 1}


def test_container_tags_are_per_user(ms):
    a = running(ms, U, "cTag_01")
    b = running(ms, V, "cTag_01")
    assert a.cid != b.cid and ms.container(U, "cTag_01") is a and ms.container(V, "cTag_01") is b
    ms.remove_container(U, "cTag_01")
    assert ms.container(V, "cTag_01") is b
    with pytest.raises(NotFound):
        ms.container(U, "cTag_01")


def test_container_lookup_errors(ms):
    with pytest.raises(NotFound, match="'nope'"):
        ms.container(U, "nope")
    with pytest.raises(NotFound):
        ms.remove_container(U, "nope")
    c = running(ms, U, "c1")
    assert ms.container_by_cid(c.cid) is c and ms.container_by_cid(999) is None


def test_container_ready(ms):
    c, _ = ms.add_container(U, "r1", "c1", None)
    ms.container_ready(c, "unix:/x", "unshare")
    assert (c.state, c.data_addr, c.sandbox) == ("running", "unix:/x", "unshare")


def test_remove_container_drops_its_nodes_and_params_only(ms):
    running(ms, U, "c1")
    running(ms, U, "c2")
    running(ms, V, "c1")
    for user, ctag in ((U, "c1"), (U, "c2"), (V, "c1")):
        ms.add_node(user, component("addNodes", {"containerTag": ctag, "nodeTag": "n", "pkg": "Test", "exe": "e"}))
        ms.set_param(user, ctag, "p", 1)
    i1 = iface(ms, U, "r1", "c1", "pub", "PublisherInterface")
    iface(ms, U, "r1", "c2", "pub", "PublisherInterface")
    wired_to = iface(ms, U, "r1", "c2", "sub", "SubscriberInterface")
    ms.connect(U, "c1/pub", "c2/sub")
    c, pairs = ms.remove_container(U, "c1")
    assert c.ctag == "c1" and pairs == [(i1, wired_to)]
    assert (U, "c1", "pub") not in ms.interfaces and ms.connections == set()
    assert set(ms.nodes) == {(U, "c2", "n"), (V, "c1", "n")}
    assert set(ms.params) == {(U, "c2", "p"), (V, "c1", "p")}


def test_nodes_and_params(ms):
    c = running(ms, U, "c1")
    spec = {"containerTag": "c1", "nodeTag": "n1", "pkg": "Test", "exe": "stringEcho.py"}
    c2, n = ms.add_node(U, component("addNodes", spec))
    assert c2 is c and n.status == "starting" and n.spec == spec and n.spec is not spec
    with pytest.raises(RequestError, match="already exists"):
        ms.add_node(U, component("addNodes", spec))
    with pytest.raises(NotFound):
        ms.add_node(U, component("addNodes", {**spec, "containerTag": "nope"}))
    assert ms.node_status(c.cid, "n1", "running", {"pid": 5}) is n and n.status == "running"
    assert ms.node_status(c.cid, "other", "running", {}) is None
    assert ms.node_status(999, "n1", "running", {}) is None
    ms.remove_node(U, "c1", "n1")
    with pytest.raises(NotFound, match="'n1'"):
        ms.remove_node(U, "c1", "n1")
    ms.set_param(U, "c1", "speed", 0.5)
    ms.set_param(U, "c1", "speed", 0.7)
    assert ms.params[(U, "c1", "speed")] == 0.7
    ms.delete_param(U, "c1", "speed")
    with pytest.raises(NotFound, match="'speed'"):
        ms.delete_param(U, "c1", "speed")
    ms.set_param(U, "c1", "none", None)                      # None is a value like any other
    ms.delete_param(U, "c1", "none")
    with pytest.raises(NotFound):
        ms.set_param(U, "nope", "x", 1)


def test_lifecycles_say_every_move_in_one_table():
    """Each state of each lifecycle has its row, naming only states of that lifecycle; a container that
    runs is never re-created without being lost first, and the master's own ``running`` follows only
    a node's ``starting``."""
    for kind, table in LIFECYCLES.items():
        assert set(table) == set(kind) and all(set(to) <= set(kind) for to in table.values())
    assert check_move(ContainerState, "container 'c'", "lost", "recovering") is ContainerState.RECOVERING
    assert check_move(ContainerState, "container 'c'", "running", "running") is ContainerState.RUNNING
    with pytest.raises(IllegalMove, match=r"^container 'c' cannot go from running to recovering "
                                          r"\(from running: lost\)$"):
        check_move(ContainerState, "container 'c'", "running", "recovering")
    assert [s for s in NodeStatus if NodeStatus.RUNNING in NODE_TRANSITIONS[s]] == [NodeStatus.STARTING]
    with pytest.raises(ValueError):
        check_move(NodeStatus, "node 'n'", "running", "flying")


def test_a_record_moves_only_as_its_lifecycle_allows_and_a_refused_move_changes_nothing(ms):
    c = running(ms, U, "c1")
    assert c.state is ContainerState.RUNNING
    _, n = ms.add_node(U, component("addNodes", {"containerTag": "c1", "nodeTag": "n1", "pkg": "Test", "exe": "e"}))
    ms.node_status(c.cid, "n1", "exited", {"code": 3})
    with pytest.raises(IllegalMove, match="node 'n1' in container 'c1' cannot go from exited to running"):
        ms.node_status(c.cid, "n1", "running", {})
    assert (n.status, n.detail) == (NodeStatus.EXITED, {"code": 3})
    ms.container_lost(c)
    ms.container_recovering(c, c.tid)
    assert (c.state, n.status) == (ContainerState.RECOVERING, NodeStatus.STARTING)
    restored = MasterState(ms.store)                  # a stored state comes back as its lifecycle's member
    assert restored.containers[(U, "c1")].state is ContainerState.RECOVERING
    assert restored.nodes[(U, "c1", "n1")].status is NodeStatus.STARTING


# -- interfaces ---------------------------------------------------------------------------------
def test_robot_side_interface_on_own_endpoint(ms):
    ms.robot_connect(U, "r1", 1)
    rec = iface(ms, U, "r1", "r1", "cmd", "SubscriberConverter", "/std_msgs/String/")
    assert (rec.kind, rec.side, rec.itype, rec.location, rec.tag, rec.cls) == \
        ("Subscriber", "Converter", "SubscriberConverter", 1, "r1/cmd", "std_msgs/String")
    assert rec.robot_side


def test_robot_side_interface_must_name_the_asking_robot(ms):
    ms.robot_connect(U, "r1", 1)
    ms.robot_connect(U, "r2", 1)
    with pytest.raises(RequestError) as ei:
        iface(ms, U, "r1", "r2", "cmd", "PublisherForwarder")
    assert "'r1'" in ei.value.message and "'r2'" in ei.value.message
    assert ms.interfaces == {}


def test_robot_side_interface_of_a_robot_not_connected(ms):
    with pytest.raises(NotFound, match="not connected"):
        iface(ms, U, "r1", "r1", "cmd", "PublisherConverter")


def test_container_side_interface_needs_the_users_container(ms):
    ms.robot_connect(U, "r1", 1)
    with pytest.raises(NotFound, match="'c1'"):
        iface(ms, U, "r1", "c1", "i", "PublisherInterface")
    running(ms, V, "c1")
    with pytest.raises(NotFound):                               # bob's container is not alice's
        iface(ms, U, "r1", "c1", "i", "PublisherInterface")
    c = running(ms, U, "c1")
    rec = iface(ms, U, "r1", "c1", "i", "PublisherInterface", addr="/chatter")
    assert rec.location == c.cid and rec.addr == "/chatter" and not rec.robot_side


def test_container_side_interface_on_a_starting_container_is_allowed(ms):
    ms.add_container(U, "r1", "c1", None)
    assert iface(ms, U, "r1", "c1", "i", "SubscriberInterface").etag == "c1"


def test_container_side_interface_on_a_lost_container(ms):
    running(ms, U, "c1")
    ms.drop_taskset(2)
    with pytest.raises(Unavailable, match="lost"):
        iface(ms, U, "r1", "c1", "i", "SubscriberInterface")


def test_duplicate_interface(ms):
    running(ms, U, "c1")
    iface(ms, U, "r1", "c1", "i", "PublisherInterface")
    with pytest.raises(RequestError, match="c1/i already exists"):
        iface(ms, U, "r1", "c1", "i", "SubscriberInterface")
    assert ms.interfaces[(U, "c1", "i")].kind == "Publisher"


def test_interface_tag_with_slash(ms):
    running(ms, U, "c1")
    with pytest.raises(RequestError, match="must not contain '/'"):
        iface(ms, U, "r1", "c1", "a/b", "PublisherInterface")


def test_unknown_interface_type(ms):
    running(ms, U, "c1")
    with pytest.raises(RCEError, match="'PublisherThing'"):
        iface(ms, U, "r1", "c1", "i", "PublisherThing")
    assert ms.interfaces == {}


def test_legacy_service_names_are_service_clients(ms):
    ms.robot_connect(U, "r1", 1)
    running(ms, U, "c1")
    a = iface(ms, U, "r1", "c1", "srv", "ServiceInterface", "Test/StringEcho")
    b = iface(ms, U, "r1", "r1", "srv", "ServiceConverter", "Test/StringEcho")
    assert (a.itype, a.kind, b.itype, b.kind) == ("ServiceClientInterface", "ServiceClient",
                                                  "ServiceClientConverter", "ServiceClient")


def test_interface_tags_scoped_per_user(ms):
    for user in (U, V):
        ms.robot_connect(user, "robot", 1)
        running(ms, user, "cTag_01", owner="robot")
        iface(ms, user, "robot", "cTag_01", "i", "PublisherInterface")
        iface(ms, user, "robot", "robot", "i", "SubscriberConverter")
    assert len(ms.interfaces) == 4 and len({r.iid for r in ms.interfaces.values()}) == 4
    ms.connect(U, "cTag_01/i", "robot/i")
    assert ms.interface(V, "cTag_01/i").iid != ms.interface(U, "cTag_01/i").iid
    ms.connect(V, "cTag_01/i", "robot/i")                       # bob's pair is separate
    assert len(ms.connections) == 2


def test_interface_lookup(ms):
    running(ms, U, "c1")
    rec = iface(ms, U, "r1", "c1", "i", "PublisherInterface")
    assert ms.interface(U, "c1/i") is rec
    for tag in ("c1/x", "c1", "x/i", ""):
        with pytest.raises(NotFound):
            ms.interface(U, tag)
    with pytest.raises(NotFound):
        ms.interface(V, "c1/i")


# -- connections --------------------------------------------------------------------------------
@pytest.fixture
def wired(ms):
    """alice: robot r1 on task set 1, running containers c1 and c2."""
    ms.robot_connect(U, "r1", 1)
    running(ms, U, "c1")
    running(ms, U, "c2")
    return ms


@pytest.mark.parametrize("a, b", [
    (("c1", "PublisherInterface"), ("r1", "SubscriberConverter")),
    (("c1", "SubscriberInterface"), ("r1", "PublisherConverter")),
    (("c1", "PublisherInterface"), ("r1", "SubscriberForwarder")),
    (("r1", "ServiceProviderConverter"), ("c1", "ServiceClientInterface")),
    (("c1", "ServiceProviderInterface"), ("r1", "ServiceClientForwarder")),
    (("c1", "PublisherInterface"), ("c2", "SubscriberInterface")),       # container to container
    (("c1", "ServiceClientInterface"), ("c2", "ServiceProviderInterface")),
])
def test_connect_valid_pairs(wired, a, b):
    ra = iface(wired, U, "r1", a[0], "a", a[1])
    rb = iface(wired, U, "r1", b[0], "b", b[1])
    x, y = wired.connect(U, f"{a[0]}/a", f"{b[0]}/b")
    assert (x, y) == (ra, rb)
    assert len(wired.connections) == 1
    conn = next(iter(wired.connections))
    assert (conn.user, conn.a, conn.b) == (U, min(ra.iid, rb.iid), max(ra.iid, rb.iid))
    with pytest.raises(RequestError, match="already connected"):
        wired.connect(U, f"{b[0]}/b", f"{a[0]}/a")               # the other order is the same connection


@pytest.mark.parametrize("ta, tb", [
    ("PublisherInterface", "PublisherConverter"),
    ("SubscriberInterface", "SubscriberConverter"),
    ("PublisherInterface", "ServiceProviderConverter"),
    ("SubscriberInterface", "ServiceClientConverter"),
    ("ServiceClientInterface", "ServiceClientConverter"),
    ("ServiceProviderInterface", "ServiceProviderForwarder"),
    ("ServiceClientInterface", "PublisherConverter"),
])
def test_connect_unpairable_kinds(wired, ta, tb):
    iface(wired, U, "r1", "c1", "a", ta)
    iface(wired, U, "r1", "r1", "b", tb)
    with pytest.raises(RequestError) as ei:
        wired.connect(U, "c1/a", "r1/b")
    assert "pairs only with" in ei.value.message and "c1/a" in ei.value.message
    assert wired.connections == set()


def test_connect_class_mismatch(wired):
    iface(wired, U, "r1", "c1", "a", "PublisherInterface", "std_msgs/String")
    iface(wired, U, "r1", "r1", "b", "SubscriberConverter", "std_msgs/Int32")
    with pytest.raises(RequestError, match="classes differ"):
        wired.connect(U, "c1/a", "r1/b")


def test_connect_two_robot_side_interfaces(wired):
    wired.robot_connect(U, "r2", 1)
    iface(wired, U, "r1", "r1", "a", "PublisherConverter")
    iface(wired, U, "r2", "r2", "b", "SubscriberForwarder")
    with pytest.raises(RequestError, match="two robot-side"):
        wired.connect(U, "r1/a", "r2/b")


def test_connect_needs_running_container(ms):
    ms.robot_connect(U, "r1", 1)
    ms.add_container(U, "r1", "c1", None)                      # still starting
    iface(ms, U, "r1", "c1", "a", "PublisherInterface")
    iface(ms, U, "r1", "r1", "b", "SubscriberConverter")
    with pytest.raises(Unavailable, match="not running"):
        ms.connect(U, "c1/a", "r1/b")
    ms.container_ready(ms.container(U, "c1"), "unix:/x", "")
    ms.connect(U, "c1/a", "r1/b")
    ms.disconnect(U, "c1/a", "r1/b")
    ms.drop_taskset(2)                                          # host lost
    with pytest.raises(Unavailable):
        ms.connect(U, "c1/a", "r1/b")


def test_connect_unknown_or_other_users_interface(wired):
    iface(wired, U, "r1", "c1", "a", "PublisherInterface")
    with pytest.raises(NotFound, match="'r1/nope'"):
        wired.connect(U, "c1/a", "r1/nope")
    wired.robot_connect(V, "rb", 1)
    iface(wired, V, "rb", "rb", "b", "SubscriberConverter")
    with pytest.raises(NotFound):
        wired.connect(U, "c1/a", "rb/b")
    with pytest.raises(NotFound):
        wired.connect(V, "c1/a", "rb/b")


def test_disconnect(wired):
    iface(wired, U, "r1", "c1", "a", "PublisherInterface")
    iface(wired, U, "r1", "r1", "b", "SubscriberConverter")
    with pytest.raises(NotFound, match="not connected"):
        wired.disconnect(U, "c1/a", "r1/b")
    wired.connect(U, "c1/a", "r1/b")
    a, b = wired.disconnect(U, "r1/b", "c1/a")                  # either order
    assert (a.tag, b.tag) == ("r1/b", "c1/a") and wired.connections == set()
    with pytest.raises(NotFound):
        wired.disconnect(U, "c1/a", "r1/b")
    wired.connect(U, "c1/a", "r1/b")                            # can connect again
    assert len(wired.connections) == 1


def test_one_interface_many_connections_and_remove_interface(wired):
    pub = iface(wired, U, "r1", "c1", "pub", "PublisherInterface")
    s1 = iface(wired, U, "r1", "r1", "s1", "SubscriberConverter")
    s2 = iface(wired, U, "r1", "c2", "s2", "SubscriberInterface")
    other_pub = iface(wired, U, "r1", "c2", "pub", "PublisherInterface")
    wired.connect(U, "c1/pub", "r1/s1")
    wired.connect(U, "c1/pub", "c2/s2")
    wired.connect(U, "c2/pub", "r1/s1")
    rec, conns = wired.remove_interface(U, "c1", "pub")
    assert rec is pub
    assert sorted((a.tag, b.tag) for a, b in conns) == [("c1/pub", "c2/s2"), ("c1/pub", "r1/s1")]
    assert {(c.a, c.b) for c in wired.connections} == {(min(other_pub.iid, s1.iid), max(other_pub.iid, s1.iid))}
    assert (U, "c1", "pub") not in wired.interfaces and s2.iid in {i.iid for i in wired.interfaces.values()}
    with pytest.raises(NotFound):
        wired.remove_interface(U, "c1", "pub")
    # the tag can be used again and gets a new iid
    again = iface(wired, U, "r1", "c1", "pub", "PublisherInterface")
    assert again.iid > other_pub.iid


def test_forget_interfaces(wired):
    a = iface(wired, U, "r1", "c1", "a", "PublisherInterface")
    b = iface(wired, U, "r1", "r1", "b", "SubscriberConverter")
    c = iface(wired, U, "r1", "c2", "c", "SubscriberInterface")
    wired.connect(U, "c1/a", "r1/b")
    wired.connect(U, "c1/a", "c2/c")
    conns = wired.forget_interfaces([a, b])
    # the a-b connection is reported once even though both ends are forgotten
    assert sorted((x.tag, y.tag) for x, y in conns) == [("c1/a", "c2/c"), ("c1/a", "r1/b")]
    assert list(wired.interfaces.values()) == [c] and wired.connections == set()


def test_robot_disconnect_forgets_its_interfaces_and_returns_owned_containers(wired):
    wired.robot_connect(U, "r2", 1)
    own = running(wired, U, "mine", owner="r1")
    running(wired, U, "theirs", owner="r2")
    running(wired, V, "mine", owner="r1")                      # bob's r1 is another robot
    i1 = iface(wired, U, "r1", "r1", "a", "PublisherConverter")
    i2 = iface(wired, U, "r1", "r1", "b", "SubscriberForwarder")
    iface(wired, U, "r2", "r2", "a", "PublisherConverter")
    ic = iface(wired, U, "r1", "mine", "x", "SubscriberInterface")
    wired.connect(U, "r1/a", "mine/x")
    assert wired.tasksets[1].robots == 2
    pairs, owned = wired.robot_disconnect(U, "r1")
    # its robot-side interfaces are gone with their connections (returned, for the shell to tell)
    assert [(a.tag, b.tag) for a, b in pairs] == [("r1/a", "mine/x")] and pairs[0][0] is i1
    assert {i.iid for i in wired.interfaces.values()} & {i1.iid, i2.iid} == set()
    assert wired.interface(U, "mine/x") is ic and wired.interface(U, "r2/a")
    assert wired.connections == set()
    owned_keys = {(c.user, c.ctag) for c in owned}
    assert owned_keys == {(U, "c1"), (U, "c2"), (U, "mine")} and own in owned   # not 'theirs', not bob's
    assert (U, "r1") not in wired.robots and wired.tasksets[1].robots == 1
    # a robot that is not connected: nothing to do
    assert wired.robot_disconnect(U, "r1") == ([], [])
    assert wired.tasksets[1].robots == 1
    # the robot ID can connect again
    wired.robot_connect(U, "r1", 1)


def test_drop_taskset_marks_containers_lost(wired):
    c1, c2 = wired.container(U, "c1"), wired.container(U, "c2")
    h2 = wired.register_taskset("container", "ch2", "hostC", {})
    c1.tid = h2.tid                                             # c1 lives on the other host
    lost, robots = wired.drop_taskset(2)
    assert lost == [c2] and robots == []
    assert c2.state == "lost" and c1.state == "running"
    assert 2 not in wired.tasksets
    with pytest.raises(Unavailable, match="lost"):
        wired.container(U, "c2")
    assert wired.container(U, "c1") is c1
    # the lost container can still be removed (the shell cleans up); no host to account on
    c, _ = wired.remove_container(U, "c2")
    assert c is c2
    assert wired.drop_taskset(2) == ([], [])


def test_a_lost_container_keeps_what_it_had_and_is_re_created_under_a_new_cid(wired):
    c1 = wired.container(U, "c1")
    pub = iface(wired, U, "r1", "c1", "p", "PublisherInterface", addr="/x")
    sub = iface(wired, U, "r1", "r1", "s", "SubscriberConverter")
    wired.connect(U, "c1/p", "r1/s")
    wired.set_param(U, "c1", "k", 7)
    n, = [wired.add_node(U, component("addNodes", {"containerTag": "c1", "nodeTag": "n", "pkg": "Test",
                                                   "exe": "e"}))[1]]
    wired.node_running(n)
    with pytest.raises(RequestError, match="not lost"):
        wired.container_recovering(c1, 2)
    lost, _ = wired.drop_taskset(2)
    assert c1 in lost and c1.state == "lost" and c1.data_addr            # its last address stays
    assert wired.connections_of(pub.iid) == [(pub, sub)] and wired.params_of(c1) == [("k", 7)]
    h = wired.register_taskset("container", "ch2", "hostC", {})
    old_cid = c1.cid
    wired.container_recovering(c1, h.tid)
    assert (c1.state, c1.tid) == ("recovering", h.tid) and c1.cid > old_cid
    assert wired.container_by_cid(old_cid) is None and wired.container_by_cid(c1.cid) is c1
    assert pub.location == c1.cid and sub.location == 1 and n.status == "starting"
    assert h.containers == 1 and wired.nodes_of(c1) == [n]
    assert wired.store.get(("interface", U, "c1", "p"))["location"] == c1.cid
    with pytest.raises(Unavailable, match="being re-created"):
        wired.container(U, "c1")
    wired.container_ready(c1, "tcp://new:1", "unconfined")
    assert wired.container(U, "c1") is c1 and c1.data_addr == "tcp://new:1"
    assert_view_is_the_store(wired)


def test_interrupted_recoveries_are_lost_again(wired):
    c1, c2 = wired.container(U, "c1"), wired.container(U, "c2")
    never_ran, _ = wired.add_container(U, "r1", "c3", None)
    wired.drop_taskset(2)
    h = wired.register_taskset("container", "ch2", "hostC", {})
    wired.container_recovering(c1, h.tid)
    assert wired.interrupted_recoveries() == [c2, c1]               # by cid: c1's is new
    assert c1.state == "lost" and never_ran.state == "lost"
    assert wired.store.get(("container", U, "c1"))["state"] == "lost"


def assert_view_is_the_store(s: MasterState) -> None:
    assert MasterState(MemoryStore(s.store.items())).snapshot() == s.snapshot()


def test_drop_robot_taskset_returns_its_robots(wired):
    other = wired.register_taskset("robot", "re2", "h", {"data_addr": "tcp://x:1"})
    wired.robot_connect(U, "r2", other.tid)
    rec = iface(wired, U, "r1", "r1", "a", "PublisherConverter")
    lost, robots = wired.drop_taskset(1)
    assert lost == [] and [r.robot for r in robots] == ["r1"]
    with pytest.raises(Unavailable, match="gone"):
        wired.data_addr(rec)


def test_data_addr(wired):
    rr = iface(wired, U, "r1", "r1", "a", "PublisherConverter")
    rc = iface(wired, U, "r1", "c1", "b", "SubscriberInterface")
    assert wired.data_addr(rr) == "tcp://10.0.0.1:10030"
    assert wired.data_addr(rc) == f"unix:/tmp/{U}-c1.sock"
    wired.add_container(U, "r1", "c3", None)
    r3 = iface(wired, U, "r1", "c3", "c", "SubscriberInterface")
    with pytest.raises(Unavailable, match="not running"):
        wired.data_addr(r3)


# -- relays ---------------------------------------------------------------------------------------
def test_robot_relay_is_stored_with_its_time(wired):
    assert wired.robot_relay(U, "r1", 1, "leader") is not None
    r = wired.robot(U, "r1")
    assert (r.relay, r.relay_since >= r.since) == ("leader", True)
    since = r.relay_since
    wired.robot_relay(U, "r1", 1, "leader")                        # the same relay: the time stays
    assert wired.robot(U, "r1").relay_since == since
    assert wired.robot_relay(U, "r1", 2, "other") is None           # not on that endpoint: nothing changes
    assert wired.robot_relay(U, "nobody", 1, "leader") is None
    wired.robot_relay(U, "r1", 1, "")                               # its own path again
    assert wired.robot(U, "r1").relay == ""
    assert MasterState(MemoryStore(wired.store.items())).robot(U, "r1").relay == ""


def test_robot_record_stored_before_relays_loads():
    from rce_master.state.model import Robot
    r = Robot.from_record({"user": U, "robot": "r1", "tid": 1, "since": 5.0})
    assert (r.relay, r.relay_since) == ("", 0.0)


# -- snapshot -----------------------------------------------------------------------------------
def test_snapshot_shape(wired):
    wired.users[U] = User.create(U, "pw")
    wired.add_node(U, component("addNodes", {"containerTag": "c1", "nodeTag": "n1", "pkg": "Test",
                                             "exe": "stringEcho.py"}))
    wired.node_status(wired.container(U, "c1").cid, "n1", "exited", {"code": 1})
    wired.set_param(U, "c1", "p", {"a": 1})
    iface(wired, U, "r1", "c1", "pub", "PublisherInterface", addr="/chatter")
    iface(wired, U, "r1", "r1", "sub", "SubscriberConverter")
    wired.connect(U, "c1/pub", "r1/sub")
    snap = wired.snapshot()
    assert json.loads(json.dumps(snap)) == snap                 # JSON-ready
    assert set(snap) == {"users", "tasksets", "robots", "containers", "nodes", "parameters", "interfaces",
                         "connections"}
    assert snap["users"] == [{"name": U, "role": "operator"}]
    assert "pw" not in json.dumps(snap["users"])
    assert [t["kind"] for t in snap["tasksets"]] == ["robot", "container"]
    assert snap["tasksets"][0]["ws_url"] == "ws://hostA:9010/" and snap["tasksets"][0]["robots"] == 1
    assert snap["tasksets"][1]["containers"] == 2 and snap["tasksets"][1]["sandbox"] == "process-group"
    assert snap["robots"] == [{"user": U, "robot": "r1", "endpoint": "re1", "since": snap["robots"][0]["since"],
                               "relay": "", "relay_since": None}]
    assert [(c["ctag"], c["host"], c["state"], c["owner"]) for c in snap["containers"]] == \
        [("c1", "ch1", "running", "r1"), ("c2", "ch1", "running", "r1")]
    assert snap["nodes"] == [{"user": U, "ctag": "c1", "ntag": "n1", "pkg": "Test", "exe": "stringEcho.py",
                              "status": "exited", "code": 1}]
    assert snap["parameters"] == [{"user": U, "ctag": "c1", "name": "p", "value": {"a": 1}}]
    assert [(i["tag"], i["type"], i["class"], i["addr"], i["connections"]) for i in snap["interfaces"]] == \
        [("c1/pub", "PublisherInterface", "std_msgs/String", "/chatter", 1),
         ("r1/sub", "SubscriberConverter", "std_msgs/String", None, 1)]
    assert snap["connections"] == [{"user": U, "tagA": "c1/pub", "tagB": "r1/sub"}]
    # a lost host shows in the containers' host column
    wired.drop_taskset(2)
    assert {c["host"] for c in wired.snapshot()["containers"]} == {"(lost)"}


def test_snapshot_of_empty_state():
    assert MasterState().snapshot() == {"users": [], "tasksets": [], "robots": [], "containers": [], "nodes": [],
                                        "parameters": [], "interfaces": [], "connections": []}


def test_roles_default_for_old_records_and_unknown_ones_are_refused():
    st = MasterState()
    old = User.create("old", "pw").to_record()
    del old["role"]                                              # a users file written before roles
    st.load_users([old])
    assert st.users["old"].role == "operator"
    assert st.add_user("ann", "pw", "viewer").role == "viewer" and st.set_user_role("ann", "admin").role == "admin"
    assert st.user_records()[0]["role"] == "admin"
    with pytest.raises(RequestError, match=r"unknown role 'boss' \(roles: viewer, operator, admin\)"):
        st.add_user("bob", "pw", "boss")
    with pytest.raises(RequestError, match="user record 1: unknown role 'root'"):
        st.load_users([{**old, "role": "root"}])
    with pytest.raises(NotFound):
        st.set_user_role("nobody", "viewer")
