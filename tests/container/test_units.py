"""Sans-I/O pieces of the container task set: argument building, respawn specs, interface
types and classes, sandbox selection, socket paths."""
from __future__ import annotations

from pathlib import Path

import pytest

from rce.errors import ConfigError, MessageError, NotFound, ProtocolError, RequestError
from rce.packages import BUILTIN_DIR
from rce_container import sandbox
from rce_container.host import MAX_SOCKET_PATH, socket_dir_for
from rce_container.interfaces import check_class, interface_kind
from rce_container.launcher import build_args, expand_directives, parse_respawn


def test_build_args_splits_like_a_shell_and_expands_directives():
    env = {"HOME_DIR": "/home/with space", "N": "3"}
    assert build_args("a 'b c' $(env N)", env) == ["a", "b c", "3"]
    # an expanded value with spaces stays one word
    assert build_args("--home=$(env HOME_DIR) x", env) == ["--home=/home/with space", "x"]
    assert build_args("$(find Test)/srv", env) == [f"{BUILTIN_DIR / 'Test'}/srv"]
    assert build_args("$(optenv MISSING) $(optenv MISSING fallback value)", env) == ["fallback value"]
    assert build_args(["$(env N)", "raw 'quotes'"], env) == ["3", "raw 'quotes'"]
    assert build_args("", env) == [] and build_args(None, env) == []
    with pytest.raises(RequestError, match="NOT_SET"):
        build_args("$(env NOT_SET)", env)
    with pytest.raises(NotFound, match="NoPkg"):
        expand_directives("$(find NoPkg)", env)
    with pytest.raises(RequestError, match="arg"):
        build_args("$(arg x)", env)
    with pytest.raises(RequestError, match="quotation"):
        build_args("'unbalanced", env)
    with pytest.raises(RequestError):
        build_args({"not": "args"}, env)


def test_parse_respawn():
    assert parse_respawn(None) == (False, 0.0, None)
    assert parse_respawn(False) == (False, 0.0, None)
    assert parse_respawn(True)[0] is True and parse_respawn(True)[2] is None
    assert parse_respawn({"delay": 0.5, "limit": 3}) == (True, 0.5, 3)
    for bad in ({"delay": -1}, {"limit": -2}, {"limit": 1.5}, {"delay": "1"}, {"retries": 3}, "yes", 3):
        with pytest.raises(RequestError, match="respawn"):
            parse_respawn(bad)


def test_interface_types_and_classes():
    assert interface_kind("PublisherInterface") == "Publisher"
    assert interface_kind("ServiceInterface") == "ServiceClient"     # RCE alpha name
    assert interface_kind("ServiceProviderInterface") == "ServiceProvider"
    with pytest.raises(RequestError, match="robot-side"):
        interface_kind("SubscriberForwarder")
    with pytest.raises(ProtocolError, match="Bogus"):
        interface_kind("BogusInterface")
    assert check_class("Publisher", "std_msgs/String") == "std_msgs/String"
    assert check_class("Subscriber", "std_msgs/msg/String") == "std_msgs/String"
    assert check_class("ServiceClient", "Test/StringEcho") == "Test/StringEcho"
    with pytest.raises(MessageError, match="Test/StringEcho"):
        check_class("Publisher", "Test/StringEcho")          # a service is not a message class
    with pytest.raises(MessageError, match="geometry_msgs/Nope"):
        check_class("Subscriber", "geometry_msgs/Nope")


def test_sandbox_selection():
    assert sandbox.select("auto") is sandbox.ProcessGroupSandbox
    assert sandbox.select("unconfined") is sandbox.ProcessGroupSandbox
    with pytest.raises(ConfigError, match="jail"):
        sandbox.select("jail")

    class Unavailable(sandbox.Sandbox):         # a stronger sandbox this host cannot run
        kind, priority = "test-unavailable", 100

        @classmethod
        def available(cls) -> bool:
            return False
    try:
        assert sandbox.select("auto") is sandbox.ProcessGroupSandbox
        with pytest.raises(ConfigError, match="not available"):
            sandbox.select("test-unavailable")
    finally:
        del sandbox.REGISTRY["test-unavailable"]


def test_socket_dir_falls_back_to_a_short_path():
    short = Path("/tmp/rt")
    assert socket_dir_for(short) == short
    deep = Path("/tmp/" + "d" * 120)
    alt = socket_dir_for(deep)
    assert alt != deep and alt == socket_dir_for(deep)                # deterministic
    assert len(str(alt / "c0000000000" / "bus.sock")) <= MAX_SOCKET_PATH
