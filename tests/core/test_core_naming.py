"""rce.interfaces.naming: ROS graph names."""
from __future__ import annotations

import pytest

from rce.plumbing.errors import RequestError
from rce.interfaces.naming import join, resolve, validate_name


@pytest.mark.parametrize("name, ns, node, expected", [
    ("/g", "/ns", None, "/g"),
    ("/a/b", "/", "n", "/a/b"),
    ("/a/b/", "/x", None, "/a/b"),
    ("/", "/ns", None, "/"),
    ("b", "/ns", None, "/ns/b"),
    ("b/c", "/ns/sub", "n", "/ns/sub/b/c"),
    ("b", "/", None, "/b"),
    ("b", "", None, "/b"),
    ("b", "ns", None, "/ns/b"),
    ("b", "/ns/", None, "/ns/b"),
    ("~p", "/ns", "n", "/ns/n/p"),
    ("~p/q", "/", "node", "/node/p/q"),
    ("~", "/ns", "n", "/ns/n"),
    ("_private_ok", "/ns", None, "/ns/_private_ok"),
    ("cmd_vel2", "/robot_1", None, "/robot_1/cmd_vel2"),
])
def test_resolve(name, ns, node, expected):
    assert resolve(name, ns, node) == expected


def test_resolve_defaults_to_root_namespace():
    assert resolve("chatter") == "/chatter"


@pytest.mark.parametrize("name", ["~p", "~"])
def test_private_name_needs_a_node(name):
    with pytest.raises(RequestError) as ei:
        resolve(name, "/ns")
    assert "private name" in ei.value.message and repr(name) in ei.value.message


@pytest.mark.parametrize("bad", ["", "1abc", "a-b", "a b", " a", "a.b", "a//b", "//a", "/~a", "~~a", "a~", "ä",
                                 "a/1b", "a/b-c", "//", None, 5])
def test_illegal_names(bad):
    with pytest.raises(RequestError) as ei:
        validate_name(bad, "topic name")
    assert "illegal topic name" in ei.value.message and repr(bad) in ei.value.message
    with pytest.raises(RequestError):
        resolve(bad, "/ns", "n")


@pytest.mark.parametrize("good", ["a", "/a", "~a", "/a/b_c/D9", "a/", "_x", "/"])
def test_legal_names(good):
    assert validate_name(good) == good


def test_join_normalises():
    assert join("/", "a") == "/a"
    assert join("/a/", "/b/") == "/a/b"
    assert join("", "") == "/"
    assert join("a//b", "c") == "/a/b/c"
