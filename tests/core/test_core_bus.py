"""rce.bus.core: topics, services and parameters of one graph, in process."""
from __future__ import annotations

import asyncio

import pytest

from rce.bus.core import Bus
from rce.plumbing.errors import MessageError, NotFound, RequestError, Timeout


@pytest.fixture
def bus() -> Bus:
    return Bus("test-bus")


# -- topics -------------------------------------------------------------------------------------
def test_publish_delivers_to_every_subscriber_and_counts(bus):
    got_a, got_b = [], []
    t = bus.advertise("/chatter", "std_msgs/String", "pub")
    sa = bus.subscribe("/chatter", "std_msgs/String", lambda p: got_a.append(p) or True, "a")
    sb = bus.subscribe("/chatter", "std_msgs/String", lambda p: got_b.append(p) or True, "b")
    assert bus.publish(t, b"one") == 2
    assert bus.publish(t, b"three") == 2
    assert got_a == got_b == [b"one", b"three"]
    assert (t.messages, t.bytes, t.dropped) == (2, 8, 0)
    assert (sa.received, sb.received) == (2, 2)


def test_publish_without_subscribers(bus):
    t = bus.advertise("/x", "std_msgs/String", "p")
    assert bus.publish(t, b"abc") == 0
    assert (t.messages, t.bytes) == (1, 3)


def test_dropped_when_deliver_returns_false(bus):
    t = bus.advertise("/scan", "sensor_msgs/LaserScan", "p")
    full = bus.subscribe("/scan", "sensor_msgs/LaserScan", lambda p: False, "slow", queue_size=1)
    ok = bus.subscribe("/scan", "sensor_msgs/LaserScan", lambda p: True, "fast")
    for _ in range(3):
        assert bus.publish(t, b"m") == 1
    assert (full.received, full.dropped) == (0, 3)
    assert (ok.received, ok.dropped) == (3, 0)
    assert t.dropped == 3
    assert bus.describe()["topics"][0]["dropped"] == 3


def test_queue_size_is_at_least_one(bus):
    assert bus.subscribe("/q", "std_msgs/String", lambda p: True, "o", queue_size=0).queue_size == 1
    assert bus.subscribe("/q", "std_msgs/String", lambda p: True, "o", queue_size=5.9).queue_size == 5


@pytest.mark.parametrize("first", ["advertise", "subscribe"])
def test_topic_type_mismatch(bus, first):
    if first == "advertise":
        bus.advertise("/t", "std_msgs/String", "p")
    else:
        bus.subscribe("/t", "std_msgs/String", lambda p: True, "s")
    with pytest.raises(MessageError) as ei:
        bus.advertise("/t", "std_msgs/Int32", "p2")
    assert all(s in ei.value.message for s in ("'/t'", "'std_msgs/String'", "'std_msgs/Int32'"))
    with pytest.raises(MessageError):
        bus.subscribe("/t", "std_msgs/Int32", lambda p: True, "s2")
    assert bus.topics["/t"].type == "std_msgs/String"
    # the refused registrations left nothing behind
    assert set(bus.topics["/t"].publishers) <= {"p"} and all(s.owner == "s" for s in bus.topics["/t"].subscriptions)


@pytest.mark.parametrize("bad", ["", "1x", "a b", "/a//b"])
def test_illegal_topic_names(bus, bad):
    with pytest.raises(RequestError):
        bus.advertise(bad, "std_msgs/String", "p")
    with pytest.raises(RequestError):
        bus.subscribe(bad, "std_msgs/String", lambda p: True, "s")
    assert bus.topics == {}


def test_gc_of_empty_topics(bus):
    bus.advertise("/t", "std_msgs/String", "p")
    bus.advertise("/t", "std_msgs/String", "p")        # same owner twice: counted
    sub = bus.subscribe("/t", "std_msgs/String", lambda p: True, "s")
    assert bus.topics["/t"].publishers == {"p": 2}
    bus.unadvertise("/t", "p")
    bus.unsubscribe(sub)
    assert "/t" in bus.topics                           # one publisher registration left
    bus.unadvertise("/t", "p")
    assert "/t" not in bus.topics
    # once empty, the name can take another type
    bus.advertise("/t", "std_msgs/Int32", "p")
    assert bus.topics["/t"].type == "std_msgs/Int32"


def test_gc_after_last_subscriber(bus):
    s1 = bus.subscribe("/t", "std_msgs/String", lambda p: True, "a")
    s2 = bus.subscribe("/t", "std_msgs/String", lambda p: True, "a")
    bus.unsubscribe(s1)
    assert bus.topics["/t"].subscriptions == [s2]
    bus.unsubscribe(s2)
    assert bus.topics == {}
    bus.unsubscribe(s2)                                 # twice: no error
    bus.unadvertise("/nothing", "x")                    # unknown: no error
    assert bus.topics == {}


def test_stale_subscription_does_not_remove_new_topic(bus):
    s = bus.subscribe("/t", "std_msgs/String", lambda p: True, "a")
    bus.unsubscribe(s)
    bus.advertise("/t", "std_msgs/Int32", "p")
    bus.unsubscribe(s)                                  # the old subscription of the old topic
    assert bus.topics["/t"].type == "std_msgs/Int32"


# -- services -----------------------------------------------------------------------------------
async def echo(payload: bytes) -> bytes:
    return payload[::-1]


async def test_service_call(bus):
    s = bus.advertise_service("/echo", "Test/StringEcho", echo, "node1")
    assert await bus.call_service("/echo", b"abc") == b"cba"
    assert await bus.call_service("/echo", b"xy", type_="Test/StringEcho") == b"yx"
    assert (s.calls, s.errors) == (2, 0)
    assert bus.describe()["services"] == [{"name": "/echo", "type": "Test/StringEcho", "provider": "node1",
                                           "calls": 2, "errors": 0}]


async def test_duplicate_provider_refused(bus):
    bus.advertise_service("/echo", "Test/StringEcho", echo, "node1")
    with pytest.raises(RequestError) as ei:
        bus.advertise_service("/echo", "Test/StringEcho", echo, "node2")
    assert "'node1'" in ei.value.message and "'/echo'" in ei.value.message
    assert bus.services["/echo"].owner == "node1"
    # the same owner may re-advertise (e.g. after a reconnect)
    bus.advertise_service("/echo", "Test/StringEcho", echo, "node1")
    # only the provider can withdraw it
    bus.unadvertise_service("/echo", "node2")
    assert "/echo" in bus.services
    bus.unadvertise_service("/echo", "node1")
    assert "/echo" not in bus.services
    bus.advertise_service("/echo", "Test/StringEcho", echo, "node2")


async def test_call_unknown_service(bus):
    with pytest.raises(NotFound) as ei:
        await bus.call_service("/nope", b"")
    assert "'/nope'" in ei.value.message and "test-bus" in ei.value.message


async def test_call_type_mismatch(bus):
    s = bus.advertise_service("/echo", "Test/StringEcho", echo, "n")
    with pytest.raises(MessageError) as ei:
        await bus.call_service("/echo", b"", type_="std_srvs/Empty")
    assert "'Test/StringEcho'" in ei.value.message and "'std_srvs/Empty'" in ei.value.message
    assert s.calls == 0


async def test_call_timeout_is_a_timeout(bus):
    never = asyncio.Event()

    async def stuck(payload: bytes) -> bytes:
        await never.wait()
        return b""

    s = bus.advertise_service("/stuck", "Test/StringEcho", stuck, "n")
    with pytest.raises(Timeout) as ei:
        await bus.call_service("/stuck", b"", timeout=0.01)
    assert "'/stuck'" in ei.value.message and "0.01" in ei.value.message
    assert (s.calls, s.errors) == (1, 1)


async def test_provider_error_propagates_and_counts(bus):
    async def broken(payload: bytes) -> bytes:
        raise MessageError("bad request")

    s = bus.advertise_service("/broken", "Test/StringEcho", broken, "n")
    with pytest.raises(MessageError, match="bad request"):
        await bus.call_service("/broken", b"")
    assert (s.calls, s.errors) == (1, 1)


def test_illegal_service_name(bus):
    with pytest.raises(RequestError):
        bus.advertise_service("no good", "Test/StringEcho", echo, "n")
    assert bus.services == {}


# -- parameters ---------------------------------------------------------------------------------
def test_param_set_get_leaf(bus):
    bus.set_param("/a", 1)
    bus.set_param("b", "x")                     # stored under a global name
    bus.set_param("/c/", [1, 2])
    assert bus.get_param("/a") == 1 and bus.get_param("/b") == "x" and bus.get_param("c") == [1, 2]
    bus.set_param("/a", 2)
    assert bus.get_param("a") == 2


def test_param_subtree(bus):
    bus.set_param("/robot", {"speed": 0.5, "limits": {"lin": 1.0, "ang": 2.0}, "name": "r1"})
    assert bus.params == {"/robot/speed": 0.5, "/robot/limits/lin": 1.0, "/robot/limits/ang": 2.0,
                          "/robot/name": "r1"}
    assert bus.get_param("/robot") == {"speed": 0.5, "limits": {"lin": 1.0, "ang": 2.0}, "name": "r1"}
    assert bus.get_param("/robot/limits") == {"lin": 1.0, "ang": 2.0}
    assert bus.get_param("/robot/limits/ang") == 2.0
    assert bus.get_param("/") == {"robot": {"speed": 0.5, "limits": {"lin": 1.0, "ang": 2.0}, "name": "r1"}}


def test_param_prefix_is_not_a_subtree(bus):
    bus.set_param("/robot_1/x", 1)
    with pytest.raises(NotFound):
        bus.get_param("/robot")


def test_param_delete_subtree(bus):
    bus.set_param("/a", {"b": 1, "c": {"d": 2}})
    bus.set_param("/ab", 3)
    bus.delete_param("/a/c")
    assert bus.get_param("/a") == {"b": 1}
    bus.delete_param("a")
    with pytest.raises(NotFound):
        bus.get_param("/a/b")
    assert bus.get_param("/ab") == 3                    # a sibling with the same prefix survives


def test_param_not_found(bus):
    with pytest.raises(NotFound) as ei:
        bus.get_param("/missing")
    assert "'/missing'" in ei.value.message
    with pytest.raises(NotFound):
        bus.delete_param("/missing")
    with pytest.raises(NotFound):
        bus.get_param("/")                              # nothing set at all


def test_param_illegal_name(bus):
    with pytest.raises(RequestError):
        bus.set_param("bad name", 1)
    with pytest.raises(RequestError):
        bus.set_param("/ok", {"bad key": 1})


def test_param_leaf_replaced_by_subtree(bus):
    bus.set_param("/a", 1)
    bus.set_param("/a", {"b": 2})
    assert bus.get_param("/a") == {"b": 2}
    assert bus.get_param("/") == {"a": {"b": 2}}


def test_param_subtree_replaced_by_leaf(bus):
    bus.set_param("/a", {"b": 2, "c": 3})
    bus.set_param("/a", 5)
    assert bus.get_param("/a") == 5
    with pytest.raises(NotFound):
        bus.get_param("/a/b")
    assert bus.get_param("/") == {"a": 5}


def test_param_child_of_a_leaf(bus):
    bus.set_param("/a", 1)
    bus.set_param("/a/b", 2)
    assert bus.get_param("/a") == {"b": 2}
    assert bus.get_param("/") == {"a": {"b": 2}}


def test_param_subtree_set_replaces_the_old_subtree(bus):
    """As on the ROS parameter server: setting a dict replaces what was under the name."""
    bus.set_param("/cfg", {"x": 1, "y": 2})
    bus.set_param("/cfg", {"x": 10})
    assert bus.get_param("/cfg") == {"x": 10}


def test_describe_shape(bus):
    bus.advertise("/b", "std_msgs/String", "p1")
    bus.subscribe("/a", "std_msgs/Int32", lambda p: True, "s1")
    bus.subscribe("/a", "std_msgs/Int32", lambda p: True, "s1")
    bus.set_param("/z", 1)
    bus.nodes["/n1"] = {"pid": 12}
    d = bus.describe()
    assert [t["name"] for t in d["topics"]] == ["/a", "/b"]
    assert d["topics"][0] == {"name": "/a", "type": "std_msgs/Int32", "publishers": [], "subscribers": ["s1"],
                              "messages": 0, "bytes": 0, "dropped": 0}
    assert d["topics"][1]["publishers"] == ["p1"]
    assert d["params"] == ["/z"] and d["services"] == [] and d["nodes"] == [{"name": "/n1", "pid": 12}]


def test_param_subtree_at_root(bus):
    bus.set_param("/", {"a": 1, "b": {"c": 2}})
    assert bus.params == {"/a": 1, "/b/c": 2}
    assert bus.get_param("/") == {"a": 1, "b": {"c": 2}}


def test_param_bad_key_changes_nothing(bus):
    bus.set_param("/cfg", {"x": 1})
    with pytest.raises(RequestError):
        bus.set_param("/cfg", {"y": 2, "bad key": 3})
    assert bus.get_param("/cfg") == {"x": 1}
