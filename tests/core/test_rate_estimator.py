"""The bulk lane's rate estimator (rce.interfaces.rate_estimator) fed by a bottleneck model, the pacer
that follows it, and TCP_INFO read from a real loopback socket (rce.transport.lane_socket)."""
from __future__ import annotations

import socket

import pytest

from rce.interfaces.pacer import AUTO, OFF, Pacer, new_pacer, parse_pacing
from rce.protocol.robot_session import ResumeOptions, RobotSession
from rce.interfaces.rate_estimator import (INITIAL_RATE, MAX_INTERVAL, NOTSENT_LIMIT, Mode, PathSample,
                                         RateEstimator)
from rce.transport.lane_socket import PacedLink, tcp_sample

STEP = 0.005          # s between samples


class Bottleneck:
    """A FIFO bottleneck of ``rate`` bytes/s behind a path of ``base`` s round trip, fed at the pacer's
    rate (or less, when the sender has less to send), as the kernel's pacing sends it. It gives what
    TCP_INFO would: bytes acked, a smoothed RTT (the base plus the queue's delay, RFC 6298's 1/8 gain
    per step), the minimum RTT."""

    def __init__(self, rate: float, base: float = 0.001):
        self.rate, self.base = rate, base
        self.queue = 0.0          # bytes waiting at the bottleneck
        self.acked = 0.0
        self.srtt = base
        self.t = 0.0
        self.delays: list[float] = []       # s of queueing delay after each step

    def step(self, est: RateEstimator, demand: float, notsent: int = 0) -> None:
        self.step_silently(est, demand)
        est.sample(PathSample(self.t, int(self.acked), self.srtt, self.base, notsent,
                              waited=STEP if demand > est.rate else 0.0))

    def step_silently(self, est: RateEstimator, demand: float) -> None:
        """One step of the path, the sender at the pacer's rate (or ``demand``), without a sample."""
        send = min(est.rate, demand) * STEP
        self.queue += send
        out = min(self.queue, self.rate * STEP)
        self.queue -= out
        self.acked += out
        self.t += STEP
        self.srtt += (self.base + self.queue / self.rate - self.srtt) / 8
        self.delays.append(self.queue / self.rate)

    def run(self, est: RateEstimator, seconds: float, demand: float) -> list[float]:
        """``seconds`` of steps; returns the pacer's rate at each."""
        rates = []
        for _ in range(int(seconds / STEP)):
            self.step(est, demand)
            rates.append(est.rate)
        return rates


LINK = 1_250_000.0     # bytes/s: 10 Mbit/s
CAMERA = 5_000_000.0   # bytes/s the application would send


def test_the_estimate_converges_to_the_link_and_the_pacer_stays_under_it():
    est, path = RateEstimator(), Bottleneck(LINK)
    path.run(est, 5, CAMERA)
    steady = path.run(est, 10, CAMERA)
    assert 0.85 * LINK <= est.estimate <= 1.05 * LINK
    assert 0.85 * LINK <= sum(steady) / len(steady) <= LINK        # the pacer's average rate: under the link
    queued = sorted(path.delays[-len(steady):])
    assert queued[len(queued) // 2] < 0.002         # the queue mostly empty
    assert queued[-1] < 0.025                       # and short while a probe runs
    assert est.probes > 5 and est.backoffs >= 1


@pytest.mark.parametrize("link", [100_000.0, 12_500_000.0, 125_000_000.0])     # 0.8, 100, 1000 Mbit/s
def test_it_converges_over_three_decades(link):
    est, path = RateEstimator(), Bottleneck(link, base=0.02)
    path.run(est, 15, 4 * link)
    assert 0.8 * link <= est.estimate <= 1.05 * link


def test_a_slower_link_is_followed_at_once():
    est, path = RateEstimator(), Bottleneck(LINK)
    path.run(est, 5, CAMERA)
    path.rate = LINK / 3
    path.run(est, 1, CAMERA)
    assert 0.8 * LINK / 3 <= est.estimate <= 1.05 * LINK / 3
    path.run(est, 3, CAMERA)
    assert path.delays[-1] < 0.025                  # the queue the change made is drained


def test_a_faster_link_is_found_by_probing():
    est, path = RateEstimator(), Bottleneck(LINK)
    path.run(est, 5, CAMERA)
    path.rate = 4 * LINK
    path.run(est, 6, 5 * LINK)
    assert est.estimate >= 0.8 * 4 * LINK


def test_an_application_sending_less_than_the_link_teaches_nothing_and_the_rate_stays_bounded():
    est, path = RateEstimator(), Bottleneck(LINK)
    path.run(est, 5, 0.2 * LINK)
    assert est.estimate is None and est.mode is Mode.STARTUP and est.backoffs == 0
    assert 0.2 * LINK <= est.rate <= 0.8 * LINK          # doubled only while it held data back
    path.run(est, 5, CAMERA)                             # then the camera: startup goes on
    assert 0.85 * LINK <= est.estimate <= 1.05 * LINK
    path.run(est, 5, 0.2 * LINK)                         # quiet again: the estimate stays
    assert 0.85 * LINK <= est.estimate <= 1.05 * LINK


def test_bytes_waiting_in_the_kernel_count_as_held_back():
    """A sender whose bytes wait in its kernel (not in the pacer) still has more to send than goes out:
    a queue on the path then gives the estimate."""
    est, path = RateEstimator(), Bottleneck(LINK)
    for _ in range(int(5 / STEP)):      # it sends just what the pacer lets out: never held back by it
        path.step(est, est.rate, notsent=2 * NOTSENT_LIMIT)
    assert est.backoffs >= 1 and 0.85 * LINK <= est.estimate <= 1.05 * LINK


def test_an_idle_spell_or_a_stalled_path_is_not_judged():
    est = RateEstimator()
    est.sample(PathSample(0.0, 0, 0.001, 0.001, 0, 0.0))
    est.sample(PathSample(MAX_INTERVAL + 1, 10_000, 0.001, 0.001, 0, 0.1))     # an idle spell: starts again
    assert est.intervals == 0
    est.sample(PathSample(MAX_INTERVAL + 1.1, 10_000, 0.5, 0.001, 0, 0.1))     # nothing acked, a queue
    assert est.intervals == 1 and est.estimate is None and est.backoffs == 0
    est.sample(PathSample(MAX_INTERVAL + 1.0, 20_000, 0.001, 0.001, 0, 0.1))   # older than the last: ignored
    assert est.samples == 3


def test_the_pacer_follows_its_estimator_and_reports_it():
    est = RateEstimator()
    pacer = Pacer(est.rate, estimator=est)
    pacer.spend(100_000, 0.0)
    pacer.waited(pacer.delay(16_384, 0.0))           # held back: the application wants more
    assert pacer.held() > 0
    path = Bottleneck(LINK)
    for _ in range(2000):
        path.step(est, CAMERA)
        pacer.observe(PathSample(path.t, int(path.acked), path.srtt, path.base, 0, STEP), path.t)
    assert pacer.rate == est.rate and pacer.held() == 0
    st = pacer.stats()
    assert st["rate_source"] == "estimated" and st["rate_mode"] in {m.value for m in Mode}
    assert 0.85 * LINK <= st["rate_estimate"] <= 1.05 * LINK
    assert Pacer(1000).stats() == {"rate_source": "configured", "rate": 1000}


def test_bytes_the_kernel_holds_unsent_are_the_pacers_debt():
    """After startup's overshoot the kernel may hold hundreds of kB unsent; the pacer lets no more out
    until the kernel is down to a burst, whatever the rate."""
    est = RateEstimator()
    pacer = Pacer(est.rate, estimator=est)
    pacer.observe(PathSample(0.0, 0, 0.001, 0.001, 0, 0.0), 0.0)
    assert pacer.delay(16_384, 0.0) == 0                       # nothing unsent: a full bucket
    pacer.observe(PathSample(0.01, 1000, 0.001, 0.001, 300_000, 0.0), 0.01)
    owed = 300_000 - pacer.burst                               # unsent beyond a burst
    assert pacer.delay(16_384, 0.01) == pytest.approx((owed + 16_384) / pacer.rate, rel=0.02)


def test_a_setting_names_the_pacing():
    assert parse_pacing("auto") == AUTO and parse_pacing(" OFF ") == OFF
    assert parse_pacing("10Mbit") == 1_250_000
    with pytest.raises(ValueError, match="'fast'"):
        parse_pacing("fast")
    assert new_pacer(OFF) is None
    assert new_pacer(None).estimator is not None and new_pacer(AUTO).rate == INITIAL_RATE
    assert new_pacer(2e6).estimator is None and new_pacer(2e6).rate == 2e6
    with pytest.raises(ValueError):
        RateEstimator(0)


def test_tcp_info_of_a_real_socket_is_read_and_the_kernel_paces_it():
    srv = socket.create_server(("127.0.0.1", 0))
    client = socket.create_connection(srv.getsockname())
    peer, _ = srv.accept()
    try:
        first = tcp_sample(client, 0.0, 1.0)
        client.sendall(b"x" * 100_000)
        got = 0
        while got < 100_000:
            got += len(peer.recv(1 << 20))
        second = tcp_sample(client, 0.5, 2.0)
        assert first is not None and second is not None
        assert second.acked - first.acked >= 100_000 and second.waited == 0.5 and second.t == 2.0
        assert 0 < second.min_rtt <= second.rtt < 1.0
        link = PacedLink(Pacer(1_000_000), client)
        assert link.kernel_pacing
        assert client.getsockopt(socket.SOL_SOCKET, 47) == 1_100_000      # SO_MAX_PACING_RATE, 10 % above
    finally:
        for s in (client, peer, srv):
            s.close()
    assert tcp_sample(client, 0.0, 3.0) is None        # closed: no sample


def test_a_sessions_lane_stats_carry_its_bulk_pacing_while_a_bulk_link_is_there():
    s = RobotSession("r", resume=ResumeOptions())
    s.attach_bulk(new_pacer(AUTO))
    bulk = s.lane_stats()["bulk"]
    assert bulk["rate_source"] == "estimated" and bulk["rate"] == INITIAL_RATE and bulk["rate_estimate"] is None
    assert s.stats()["lanes"]["bulk"]["rate_mode"] == "startup"
    s.detach_bulk()
    assert "rate" not in s.lane_stats()["bulk"]
    s.attach_bulk(new_pacer(2e6))
    assert s.lane_stats()["bulk"]["rate_source"] == "configured"


class BurstyAcks(Bottleneck):
    """The same bottleneck seen from a loaded host: TCP_INFO's bytes acked move only every ``every`` s,
    by what was acked since (one interval's count is then 0 or a multiple of the link's rate)."""

    def __init__(self, rate: float, every: float = 0.06):
        super().__init__(rate)
        self.every, self.shown, self.next_show = every, 0.0, every

    def step(self, est: RateEstimator, demand: float, notsent: int = 0) -> None:
        self.step_silently(est, demand)
        if self.t >= self.next_show:
            self.shown, self.next_show = self.acked, self.next_show + self.every
        est.sample(PathSample(self.t, int(self.shown), self.srtt, self.base, notsent,
                              waited=STEP if demand > est.rate else 0.0))


def test_acks_in_bursts_keep_the_estimate_near_the_link_and_the_queue_short():
    """On a loaded host acks arrive in bursts (here every 60 ms): startup's estimate is read over 160 ms,
    not one interval, and a drain lasts until the round trip shows the queue gone, so no burst sets the
    estimate far from the link, and after startup the queue stays short."""
    est, path = RateEstimator(), BurstyAcks(LINK)
    path.run(est, 15, CAMERA)
    assert 0.8 * LINK <= est.estimate <= 1.1 * LINK
    assert max(path.delays[int(2 / STEP):]) < 0.03


def test_a_drain_lasts_while_the_round_trip_shows_a_queue():
    """The path acking more than the drain's rate means the queue is draining, not that it is gone."""
    est = RateEstimator()
    est.estimate, est.mode, est.rate = LINK, Mode.DRAIN, 0.75 * LINK
    t, acked = 0.0, 0
    est.sample(PathSample(t, acked, 0.03, 0.001, 0, 0.0))
    for _ in range(2):                       # a 29 ms queue, the path acking the link's rate: still draining
        t, acked = t + 0.1, acked + int(0.1 * LINK)
        est.sample(PathSample(t, acked, 0.03, 0.001, 0, 0.1))
        assert est.mode is Mode.DRAIN
    t, acked = t + 0.1, acked + int(0.1 * 0.75 * LINK)
    est.sample(PathSample(t, acked, 0.002, 0.001, 0, 0.1))      # the queue gone: cruise
    assert est.mode is Mode.CRUISE and est.rate == pytest.approx(0.9 * LINK)



def test_a_round_trip_that_stays_high_while_the_path_acks_what_is_sent_ends_the_drain():
    """A loaded receiver (or another flow's queue) keeps the round trip up though the path acks all
    the drain sends: that is no queue of the link's, so the pacer cruises again and the estimate stays."""
    est = RateEstimator()
    est.estimate, est.mode, est.rate = LINK, Mode.DRAIN, 0.75 * LINK
    t, acked = 0.0, 0
    est.sample(PathSample(t, acked, 0.05, 0.001, 0, 0.0))
    while est.mode is Mode.DRAIN and t < 1.0:
        t, acked = t + 0.1, acked + int(0.1 * 0.75 * LINK)
        est.sample(PathSample(t, acked, 0.05, 0.001, 0, 0.1))
    assert est.mode is Mode.CRUISE and est.estimate == LINK and t == pytest.approx(0.4)


def test_startup_ends_when_a_doubling_no_longer_raises_what_the_path_acks():
    """Where the round trip shows the queue late or not at all (the kernel holds what the path does not
    take), startup ends at the full pipe: a doubling that raised the acked rate by less than 25 %."""
    class Unseen(Bottleneck):
        def step(self, est: RateEstimator, demand: float, notsent: int = 0) -> None:
            self.step_silently(est, demand)
            est.sample(PathSample(self.t, int(self.acked), self.base, self.base, 0, STEP))   # a flat RTT

    est, path = RateEstimator(), Unseen(LINK)
    rates = path.run(est, 2, CAMERA)
    assert est.estimate is not None and 0.8 * LINK <= est.estimate <= 1.05 * LINK
    assert max(rates) <= 4 * LINK                  # one or two doublings past the link, not on and on


def test_startups_drain_leads_to_probing():
    """Startup's estimate is read over a ramp and may be low: once its queue is drained the estimator
    probes at once rather than cruising under it for 16 intervals (BBR's drain leads to probing)."""
    est, path = RateEstimator(), Bottleneck(LINK)
    modes: list[Mode] = []
    for _ in range(int(2 / STEP)):
        path.step(est, CAMERA)
        if not modes or modes[-1] is not est.mode:
            modes.append(est.mode)
    assert modes[:3] == [Mode.STARTUP, Mode.DRAIN, Mode.PROBE], modes
