"""The relay hop's wire, sans I/O (rce_client/tunnel.py): CONNECT heads, answers, HOST:PORT; the relay's
pacer; a follower's --relays list."""
from __future__ import annotations

import pytest

from rce_client.relay import RelayPacer
from rce_client.routes import parse_relays
from rce_client.tunnel import (HeadError, answer, connect_request, parse_answer, parse_request, split_hostport,
                               url_addr)


def test_connect_request_round_trip():
    head = connect_request(("10.0.0.1", 9000))
    assert head == b"CONNECT 10.0.0.1:9000 HTTP/1.1\r\nHost: 10.0.0.1:9000\r\n\r\n"
    assert parse_request(head[:-4]) == ("10.0.0.1", 9000)
    assert parse_request(connect_request(("::1", 443))[:-4]) == ("::1", 443)


@pytest.mark.parametrize("head, why", [
    (b"GET / HTTP/1.1\r\nHost: x", "only CONNECT"),
    (b"CONNECT example.org HTTP/1.1", "HOST:PORT"),
    (b"CONNECT a:0 HTTP/1.1", "HOST:PORT"),
    (b"CONNECT a:99999 HTTP/1.1", "HOST:PORT"),
    (b"hello", "request line"),
])
def test_bad_request_heads_are_named(head, why):
    with pytest.raises(HeadError, match=why):
        parse_request(head)


def test_answers_round_trip():
    ok = answer(200, name="L1")
    head, _, rest = ok.partition(b"\r\n\r\n")
    assert parse_answer(head, rest) == (200, "L1")
    full = answer(503, "relay L1 is full: it carries 4 follower(s) already")
    head, _, body = full.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503 Service Unavailable")
    assert parse_answer(head, body) == (503, "relay L1 is full: it carries 4 follower(s) already")
    with pytest.raises(HeadError):
        parse_answer(b"SSH-2.0-OpenSSH")


def test_hostports_and_urls():
    assert split_hostport("[fe80::1]:80", "x") == ("fe80::1", 80)
    assert url_addr("wss://h:9443/?a=1") == ("h", 9443) and url_addr("https://h/") == ("h", 443)
    assert parse_relays("10.0.0.1:9100, l2:9100") == [("10.0.0.1", 9100), ("l2", 9100)]
    with pytest.raises(ValueError, match="--relays"):
        parse_relays("10.0.0.1")
    with pytest.raises(ValueError, match="nothing"):
        parse_relays(" , ")


def test_pacer_delays_past_the_rate():
    p = RelayPacer(1000.0, 500.0)
    t = p.stamp
    assert p.delay(500, t) == 0.0                  # the burst
    assert p.delay(500, t) == pytest.approx(0.5)   # 500 bytes more at 1000 bytes/s
    assert p.delay(100, t + 0.6) == pytest.approx(0.0, abs=1e-9)   # 600 bytes earned, 500 owed
    assert RelayPacer(0, 0).delay(10**9, t) == 0.0  # no pacing
