"""The tests' etcd (tests/etcd_server.py) when another server takes its port between the moment the
port was found free and etcd's bind, as a test's etcd in another pytest-xdist worker may: it starts
again on new ports and answers as itself, so pausing it stops the etcd the test talks to."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import etcd_server  # noqa: E402
from etcd_server import EtcdServer  # noqa: E402


def test_an_etcd_whose_port_another_holds_starts_again_as_itself(tmp_path, monkeypatch):
    with EtcdServer(tmp_path / "a") as a:
        found_free = etcd_server.free_port
        taken = [a.port]                                    # the first port "found free" is a's
        monkeypatch.setattr(etcd_server, "free_port", lambda: taken.pop() if taken else found_free())
        with EtcdServer(tmp_path / "b") as b:
            assert not taken and b.port != a.port
            assert b"address already in use" in (tmp_path / "b" / "etcd.log").read_bytes()
            assert b.member_name() == b.name and a.member_name() == a.name != b.name
            b.pause()
            try:
                assert a.member_name() == a.name            # the pause stopped b, and a still answers
                with pytest.raises(OSError):
                    b.member_name()                         # b does not
            finally:
                b.resume()
            assert b.member_name() == b.name
