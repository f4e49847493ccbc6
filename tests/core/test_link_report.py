"""Robots' links as the placer sees them (rce_robot.link_report) on real loopback TCP sockets: an
endpoint on a robot's computer measures its uplink, keeps the last rate it measured (a busy link's,
or its probes', the fastest of the last PROBE_KEEP_S s); reports go out when a link moved."""
from __future__ import annotations

import socket

from rce.transport.lane_socket import link_sample
import pytest

from rce_robot.link_report import CHANGE, PROBE_BYTES, PROBE_EVERY, PROBE_KEEP_S, LinkReports, Uplink, probe_rate


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


def test_the_uplink_keeps_a_busy_links_rate_until_a_probe_says_otherwise():
    a, b = busy_pair()
    try:
        rtt, rate, app_limited = link_sample(a)
        assert rtt >= 0 and rate > 0 and not app_limited, (rtt, rate, app_limited)
        data = [a]
        up = Uplink(lambda: a, lambda: data)
        rtt_s, measured = up.measure(100.0)
        assert measured > 0
        data.clear()                                        # its container moved: the link idles
        assert up.measure(100.0 + 600)[1] == measured, "an idle link is as thin as it was last measured"
        up.probed(701.0, 125_000.0)                         # probes: 1 Mbit/s, then the link is back
        assert up.measure(701.0)[1] == 125_000.0
        up.probed(702.0, 5e6)
        up.probed(702.5, 2e6)                               # a probe whose answers were read late: the fastest stands
        assert up.rate == 5e6
        up.probed(702.5 + PROBE_KEEP_S + 0.5, 1e6)          # the fast ones are too old now
        assert up.rate == 1e6
        assert PROBE_EVERY < PROBE_KEEP_S, "each window holds a probe"
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


def test_a_probe_is_the_spacing_of_two_answers():
    assert probe_rate(10.0, 10.128) == pytest.approx(PROBE_BYTES / 0.128)     # 16 kB in 128 ms: 1 Mbit/s
    assert probe_rate(10.0, 10.0) == pytest.approx(PROBE_BYTES / 1e-4), "below the grain: bounded"
