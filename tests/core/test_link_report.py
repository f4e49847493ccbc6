"""Robots' links as the placer sees them (rce_robot.link_report) on real loopback TCP sockets: an
endpoint on a robot's computer measures its uplink, keeps a rate it measured while a link was busy
for RATE_HOLD s, then forgets it; reports go out when a link moved."""
from __future__ import annotations

import socket

from rce.transport.lane_socket import link_sample
from rce_robot.link_report import CHANGE, RATE_HOLD, LinkReports, Uplink


def busy_pair() -> tuple[socket.socket, socket.socket]:
    """A connected loopback pair whose sender has filled the receiver's window (not app-limited)."""
    srv = socket.create_server(("127.0.0.1", 0))
    a = socket.create_connection(srv.getsockname())
    b, _ = srv.accept()
    srv.close()
    a.setblocking(False)
    chunk = b"x" * 65536
    try:
        while True:
            a.send(chunk)
    except BlockingIOError:
        pass
    for _ in range(20):                   # the receiver takes some, so that deliveries are measured
        b.recv(1 << 20)
        try:
            while True:
                a.send(chunk)
        except BlockingIOError:
            pass
    return a, b


def test_the_uplink_keeps_a_busy_links_rate_for_its_hold_then_forgets_it():
    a, b = busy_pair()
    try:
        rtt, rate, app_limited = link_sample(a)
        assert rtt >= 0 and rate > 0 and not app_limited, (rtt, rate, app_limited)
        data = [a]
        up = Uplink(lambda: a, lambda: data)
        rtt_s, measured = up.measure(100.0)
        assert measured > 0
        data.clear()                                        # its container moved: the link idles
        assert up.measure(100.0 + RATE_HOLD / 2)[1] == measured
        assert up.measure(100.0 + RATE_HOLD + 1)[1] == 0.0, "an idle link's rate is unknown after the hold"
        assert Uplink(lambda: None, lambda: data).measure(0.0) is None, "no link to the master: not measured"
    finally:
        a.close()
        b.close()


def test_a_report_goes_out_when_a_link_moved_and_not_otherwise():
    sent = []
    reports = LinkReports(lambda *args: sent.append(args))
    assert reports.sample(0.0, [("u", "r", (0.010, 1e6)), ("u", "s", None)]) == 1
    assert reports.sample(0.5, [("u", "r", (0.010 * (1 + CHANGE / 2), 1e6))]) == 0
    assert reports.sample(1.0, [("u", "r", (0.010 * (1 + 2 * CHANGE), 1e6))]) == 1
    assert [s[:2] for s in sent] == [("u", "r"), ("u", "r")] and sent[0][2] == 10.0
