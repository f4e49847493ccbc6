"""Robots' links as the placer sees them (rce_robot.link_report) on real loopback TCP sockets: an
endpoint on a robot's computer measures its uplink, keeps the last rate it measured (a busy link's,
or its probes', the fastest of the last PROBE_KEEP_S s; a backed-up link's throughput alone);
reports go out when a link moved."""
from __future__ import annotations

import contextlib
import socket
import threading
import time

from rce.transport.lane_socket import SO_MAX_PACING_RATE, link_sample
import pytest

from rce_robot.link_report import (BACKLOG_S, CHANGE, EVERY, PING_KEEP_S, PROBE_BYTES, PROBE_EVERY, PROBE_KEEP_S,
                                   LinkReports, Uplink, crosses_uplink, probe_rate)


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


PACED = 200_000          # bytes/s the kernel lets the "thin link" socket send (SO_MAX_PACING_RATE)


def paced_pair() -> tuple[socket.socket, socket.socket, list[threading.Thread]]:
    """A loopback pair whose sender the kernel paces at PACED bytes/s in small segments, with a
    writer that has far more to send than that and a reader that takes everything at once: a link
    that is the bottleneck (bytes wait unsent), not its reader."""
    srv = socket.socket()
    srv.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, 1400)
    srv.bind(("127.0.0.1", 0))
    srv.listen()
    a = socket.socket()
    a.setsockopt(socket.IPPROTO_TCP, socket.TCP_MAXSEG, 1400)
    a.connect(srv.getsockname())
    b, _ = srv.accept()
    srv.close()
    a.setsockopt(socket.SOL_SOCKET, SO_MAX_PACING_RATE, PACED)

    def read() -> None:
        with contextlib.suppress(OSError):
            while b.recv(1 << 20):
                pass

    def write() -> None:
        with contextlib.suppress(OSError):          # closed at the end of the test
            a.sendall(b"x" * (10 * PACED))
    threads = [threading.Thread(target=f, daemon=True) for f in (read, write)]
    for t in threads:
        t.start()
    return a, b, threads


def look(up: Uplink, looks: int) -> float:
    """The uplink's rate after ``looks`` looks EVERY s apart (the endpoint's own cadence: what is
    measured is bytes over that time)."""
    for _ in range(looks):
        time.sleep(EVERY)
        up.measure(time.monotonic())
    return up.rate


def test_a_backed_up_link_is_measured_at_once_and_a_slow_reader_is_not_a_thin_link():
    a, b, threads = paced_pair()
    quiet, idle = busy_pair()                       # a control link: its own peer, nothing to say
    try:
        up = Uplink(lambda: quiet, lambda: [a])
        up.probed(time.monotonic(), 50e6)          # the link was fast a moment ago
        rate = look(up, int(BACKLOG_S / EVERY) + 2)
        assert up.backed_up >= 1 and up.waiting, "bytes waited at every look: the link is the bottleneck"
        assert PACED / 3 < rate < PACED * 3, (rate, "what it carried, whatever was measured before")
        up.probed(time.monotonic(), 40e6)          # a probe right after: the fastest of the window again
        assert up.rate == 40e6
    finally:
        for s in (a, b):
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)          # the writer and the reader end
        for s in (a, b, quiet, idle):
            s.close()
        for t in threads:
            t.join(5)
    # a reader that does not read: bytes wait too, but for its receive window, not for the link
    c, d = busy_pair()
    try:
        up = Uplink(lambda: c, lambda: [c])
        up.probed(time.monotonic(), 50e6)
        look(up, int(BACKLOG_S / EVERY) + 2)
        assert up.backed_up == 0 and up.rate >= 50e6, "its backlog is its reader's: the link is not thin"
        assert not crosses_uplink(c), "a link on this computer says nothing of the uplink"
    finally:
        c.close()
        d.close()


def test_the_uplinks_round_trip_is_its_pings_least_of_late_and_the_kernels_without_them():
    a, b = busy_pair()
    try:
        up = Uplink(lambda: a, lambda: [])
        kernel_rtt = link_sample(a)[0]
        assert up.measure(10.0)[0] == kernel_rtt, "no ping yet: the kernel's smoothed round trip"
        up.pinged(10.0, 0.010)
        assert up.measure(10.1)[0] == 0.010
        up.pinged(10.25, 0.105)                         # the link's delay grew: one ping is not the link yet
        assert up.measure(10.3)[0] == 0.010
        up.pinged(10.5, 0.400)                          # one that waited behind a burst
        up.pinged(10.75, 0.102)
        assert up.measure(10.8)[0] == 0.102, "once the fast one is older than PING_KEEP_S, the link is slow"
        up.pinged(11.0, 0.011)                          # the link is back: the first fast ping says so
        assert up.measure(11.0)[0] == 0.011
        assert up.measure(11.0 + PING_KEEP_S + 0.1)[0] == kernel_rtt, "pings that old say nothing"
    finally:
        a.close()
        b.close()


def test_a_probe_keeps_out_of_the_way_of_a_link_that_fell():
    from rce_robot.link_report import PROBE_HOLD_S, PROBE_SHARE, PROBE_DRAIN_BYTES
    up = Uplink(lambda: None, lambda: [])
    up.rate = 12.5e6                                        # 100 Mbit/s
    for k in range(4):
        up.pinged(10.0 + 0.25 * k, 0.010)
    assert up.probe_due(11.0, 9.9) and not up.probe_due(11.0, 10.5), "every PROBE_EVERY s on a fast link"
    up.pinged(11.25, 0.101)                                 # the link fell: 10 -> 101 ms
    assert up.rtt_rose and not up.probe_due(11.3, 9.0), "no probe while containers may move across it"
    assert up.probe_due(11.25 + PROBE_HOLD_S, 9.0), "then one, at once: its rate moved too"
    up.rate = 125_000.0                                     # it measured 1 Mbit/s
    probed = 13.3
    gap = (PROBE_DRAIN_BYTES + PROBE_BYTES) / up.rate / PROBE_SHARE
    assert not up.probe_due(probed + PROBE_EVERY, probed) and up.probe_due(probed + gap, probed), \
        f"at 1 Mbit/s a probe goes every {gap:.1f} s: {PROBE_SHARE:.0%} of the link's time"
    up.pinged(probed + 0.75, 0.101)
    up.pinged(probed + 1.0, 0.010)                          # the link is back: a probe at once (it is quick now)
    assert not up.rtt_rose and up.probe_due(probed + 1.0, probed)
    up.waiting = True
    assert not up.probe_due(probed + 100.0, probed), "never while a data link waits for the uplink"
