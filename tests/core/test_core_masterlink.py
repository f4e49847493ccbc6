"""rce.transport.masterlink: a task set's control link that outlives its master. The backoff and the
address list are pure; the link runs against masters played on in-memory links (no sockets),
its backoff delays recorded instead of slept, and once over real loopback TCP. Every link,
re-registrations included, opens with the cluster handshake (:mod:`rce.transport.cluster_auth`)."""
from __future__ import annotations

import asyncio
import time

import pytest
from memlink import pipe

from rce.transport.cluster_auth import AuthFailed, ClusterKey, respond
from rce.plumbing.errors import ConfigError, NotLeader, RequestError, Unavailable
from rce.transport.masterlink import Backoff, MasterLink, parse_masters, unless_stopped
from rce.transport.rpc import RpcPeer

STEP = 5.0          # s, the longest any single wait may take
A, B, C = ("10.0.0.1", 8080), ("10.0.0.2", 8080), ("10.0.0.9", 7000)
INFO = {"kind": "container", "name": "h1", "host": "10.0.0.5"}
KEY = ClusterKey.generate()


# -- the backoff and the address list ------------------------------------------------------------------
def test_backoff_doubles_up_to_its_cap():
    b = Backoff(initial=0.05, factor=2, cap=2.0, jitter=0.5, rng=lambda: 0.0)
    assert [round(b.next(), 6) for _ in range(9)] == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0, 2.0]
    for _ in range(10_000):            # no overflow however long the master stays away
        assert b.next() == 2.0
    b.reset()
    assert b.next() == 0.05


def test_backoff_jitter_shortens_each_delay_by_up_to_its_fraction():
    draws = iter([0.0, 0.5, 0.999999, 0.25])
    b = Backoff(initial=1.0, factor=2, cap=4.0, jitter=0.5, rng=lambda: next(draws))
    assert [round(b.next(), 4) for _ in range(4)] == [1.0, 1.5, 2.0, 3.5]
    real = Backoff(initial=1.0, factor=1, cap=1.0, jitter=0.3)
    assert all(0.7 <= real.next() <= 1.0 for _ in range(1000))


@pytest.mark.parametrize("kw", [{"initial": 0}, {"initial": 3, "cap": 2}, {"factor": 0.5}, {"jitter": 1.0},
                                {"jitter": -0.1}])
def test_backoff_refuses_settings_that_make_no_sense(kw):
    with pytest.raises(ConfigError, match="backoff: need"):
        Backoff(**kw)


def test_master_addresses():
    assert parse_masters("m1", 8080) == [("m1", 8080)]
    assert parse_masters("m1:9000, m2,[::1]:7000,::1,[fe80::1]", 8080) == [
        ("m1", 9000), ("m2", 8080), ("::1", 7000), ("::1", 8080), ("fe80::1", 8080)]
    assert parse_masters(["a:1", "b"], 2) == [("a", 1), ("b", 2)]
    for bad, why in [("m1:http", "port 'http' is not a number"), ("m1:0", "1..65535"), (":80", "HOST"),
                     ("[::1", r"\[IPV6\]"), ("m1,,m2", "HOST"), ("[::1]x", r"\[IPV6\]")]:
        with pytest.raises(ConfigError, match=why):
            parse_masters(bad)
    with pytest.raises(ConfigError, match="no master"):
        parse_masters([])


# -- masters played on in-memory links -----------------------------------------------------------------------
class FakeMaster:
    """One master: takes dials while ``up``; answers ``register`` (``refusals`` first, one per
    register), records what arrives in ``events`` and serves ``echo``."""

    def __init__(self, tid: int = 7, key: ClusterKey = KEY):
        self.tid, self.up, self.key = tid, True, key
        self.handshakes = 0                            # links that proved the key
        self.serving: set[asyncio.Future] = set()      # handshakes under way
        self.refusals: list[Exception] = []
        self.events: list[tuple[str, dict]] = []       # ("register", args) and ("note", args), in order
        self.registers: asyncio.Queue = asyncio.Queue()
        self.peers: list[RpcPeer] = []

    def accept(self):
        (ra, wa), (rb, wb) = pipe()
        self.serving.add(t := asyncio.ensure_future(self._serve(rb, wb)))
        t.add_done_callback(self.serving.discard)
        return ra, wa

    async def _serve(self, reader, writer) -> None:
        try:
            await respond(reader, writer, self.key)
        except AuthFailed:
            writer.close()
            return
        self.handshakes += 1
        peer = RpcPeer(reader, writer, {"register": self._register, "note": self._note, "echo": self._echo},
                       name="task set").start()
        self.peers.append(peer)

    async def _register(self, args: dict) -> dict:
        if self.refusals:
            raise self.refusals.pop(0)
        self.events.append(("register", args))
        self.registers.put_nowait(args)
        return {"tid": args.get("tid") or self.tid, "resumed": "tid" in args, "drop_containers": [3]}

    async def _note(self, args: dict) -> None:
        self.events.append(("note", args))

    async def _echo(self, args: dict) -> dict:
        return args

    async def next_register(self) -> dict:
        return await asyncio.wait_for(self.registers.get(), STEP)

    def kill(self, stay_down: bool = True) -> None:
        """The master dies: its links close; it takes no dial until ``up`` again."""
        self.up = not stay_down
        for p in self.peers:
            p.link.close("killed")

    def notes(self) -> list[dict]:
        return [a for kind, a in self.events if kind == "note"]


class Net:
    """Where masters listen; ``dials`` records every attempt, ``delays`` every backoff delay."""

    def __init__(self, **masters: FakeMaster):
        self.masters = {addr: m for addr, m in zip((A, B, C), (masters.get("a"), masters.get("b"), masters.get("c")),
                                                   strict=True) if m is not None}
        self.dials: list[tuple[str, int]] = []
        self.delays: list[float] = []
        self.on_sleep = lambda n: None            # called with the number of delays so far
        self.real = False                         # True: delays are slept (else recorded only)

    async def dial(self, addr):
        self.dials.append(addr)
        m = self.masters.get(addr)
        if m is None or not m.up:
            raise ConnectionRefusedError(111, f"connection to {addr} refused")
        return m.accept()

    async def sleep(self, delay: float) -> None:
        self.delays.append(delay)
        self.on_sleep(len(self.delays))
        await asyncio.sleep(delay if self.real else 0)


def link(net: Net, masters=(A,), **kw) -> MasterLink:
    kw.setdefault("backoff", Backoff(rng=lambda: 0.0))
    return MasterLink(list(masters), {}, INFO, dial=net.dial, sleep=net.sleep, cluster_key=KEY, **kw)


async def started(**kw) -> tuple[FakeMaster, Net, MasterLink]:
    """One master, and a link (``link(**kw)``) registered with it, its first register taken."""
    m = FakeMaster()
    net = Net(a=m)
    ml = link(net, **kw)
    await ml.start()
    await m.next_register()
    return m, net, ml


async def until(pred, what: str) -> None:
    deadline = time.monotonic() + STEP
    while not pred():
        assert time.monotonic() < deadline, what
        await asyncio.sleep(0.005)


async def test_registers_then_re_registers_with_its_tid_and_report_on_every_reconnect():
    m = FakeMaster()
    net = Net(a=m)
    held = []
    answers = []

    async def obey(answer):
        answers.append(answer)
    ml = link(net, report=lambda: {"containers": list(held)}, on_registered=obey)
    assert await ml.start() == {"tid": 7, "resumed": False, "drop_containers": [3]}
    assert await m.next_register() == INFO and ml.tid == 7 and ml.available
    for n in range(1, 4):
        held.append(n)
        m.kill(stay_down=False)                # the link drops; the master takes the next dial
        assert await m.next_register() == {**INFO, "tid": 7, "containers": list(range(1, n + 1))}
        await until(lambda: ml.available, "available again")
    assert ml.registrations == 4 and [a["resumed"] for a in answers] == [False, True, True, True]
    assert net.delays == []                    # a link that drops is dialled again at once
    await ml.close()


async def test_a_master_without_the_cluster_key_is_a_mistake_at_first_and_an_outage_later():
    impostor = FakeMaster(key=ClusterKey.generate())
    with pytest.raises(AuthFailed, match="cluster keys differ"):
        await link(Net(a=impostor)).start()
    assert impostor.events == [] and impostor.handshakes == 0
    m, net, ml = await started()
    assert m.handshakes == 1
    m.kill()
    net.masters[A] = impostor                 # someone else answers at the master's address meanwhile

    def back(n: int) -> None:                 # the real master is back after 3 failed rounds
        if n == 3:
            m.up, net.masters[A] = True, m
    net.on_sleep = back
    assert await m.next_register() == {**INFO, "tid": 7}        # re-registered with the real master only
    assert m.handshakes == 2 and impostor.events == [] and ml.attempts >= 1 + 3
    await ml.close()


async def test_dials_with_backoff_and_no_limit_until_the_master_is_back():
    m, net, ml = await started()
    m.kill()
    net.on_sleep = lambda n: setattr(m, "up", n == 40)    # back after 40 failed rounds
    await m.next_register()
    assert [round(d, 6) for d in net.delays] == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6] + [2.0] * 34, net.delays
    assert ml.attempts == 1 + 41
    net.delays.clear()
    m.kill()                                   # away again: the backoff starts over
    net.on_sleep = lambda n: setattr(m, "up", n == 3)
    await m.next_register()
    assert [round(d, 6) for d in net.delays] == [0.05, 0.1, 0.2]
    await ml.close()


async def test_tries_each_master_in_turn_from_the_last_that_worked():
    a, b = FakeMaster(), FakeMaster()
    a.up = False
    net = Net(a=a, b=b)
    ml = link(net, masters=(A, B))
    await ml.start()
    await b.next_register()
    assert net.dials == [A, B] and ml.address == B and net.delays == []
    b.kill()
    a.up = True
    await a.next_register()
    await until(lambda: ml.available, "registered at A")
    assert net.dials == [A, B, B, A] and ml.address == A and net.delays == []
    a.kill()                                   # both down: one delay per round over both
    net.on_sleep = lambda n: setattr(b, "up", n == 2)
    await b.next_register()
    assert net.dials[4:] == [A, B, A, B, A, B] and len(net.delays) == 2
    await ml.close()


async def test_a_standby_sends_the_link_to_the_leader_at_once():
    standby, leader = FakeMaster(), FakeMaster(tid=9)
    standby.refusals = [NotLeader("register: this master stands by", leader={"control": "10.0.0.9:7000"})]
    net = Net(a=standby, c=leader)             # the leader is not in the task set's list
    ml = link(net, masters=(A,))
    assert (await ml.start())["tid"] == 9
    await leader.next_register()
    assert net.dials == [A, C] and ml.address == C and net.delays == []
    leader.kill()                              # the leader dies: its address is tried first, then the list
    standby.refusals = [NotLeader("register: no leader is elected now; try again in 2 s")]
    net.on_sleep = lambda n: setattr(leader, "up", n == 1)
    await leader.next_register()
    assert net.dials[2:] == [C, A, C] and len(net.delays) == 1
    await ml.close()


async def test_a_standby_naming_another_standby_is_not_followed_round_and_round():
    a, b = FakeMaster(), FakeMaster()
    a.refusals = [NotLeader("stands by", leader={"control": "10.0.0.2:8080"})] * 3
    b.refusals = [NotLeader("stands by", leader={"control": "10.0.0.1:8080"})] * 3
    net = Net(a=a, b=b)
    ml = link(net, masters=(A,))
    assert (await ml.start())["tid"] == 7
    assert net.dials == [A, B, A, B, A, B, A] and len(net.delays) == 3     # one hop per round, then backoff
    await ml.close()


async def test_a_leader_that_is_no_address_counts_as_a_failed_dial():
    a = FakeMaster()
    a.refusals = [NotLeader("stands by", leader={"control": "leader:http"})]
    net = Net(a=a)
    ml = link(net)
    assert (await ml.start())["tid"] == 7
    assert net.dials == [A, A] and len(net.delays) == 1
    await ml.close()


async def test_calls_wait_for_the_master_up_to_master_wait():
    m, net, ml = await started(master_wait=0.2, backoff=Backoff(initial=0.01, cap=0.02))
    net.real = True                            # real delays: the master comes back while a call waits
    assert await ml.call("echo", x=1) == {"x": 1}
    m.kill()
    await until(lambda: not ml.available, "the master seen away")
    t0 = time.monotonic()
    with pytest.raises(Unavailable, match=r"^the master is unavailable \(waited 0.2 s\)$"):
        await ml.call("echo", x=2)
    assert time.monotonic() - t0 >= 0.2
    waiting = asyncio.ensure_future(ml.call("echo", x=3))
    await asyncio.sleep(0.05)                  # the call waits for the master ...
    assert not waiting.done()
    m.up = True                                # ... which is back in time
    assert await asyncio.wait_for(waiting, STEP) == {"x": 3}
    await ml.close()


async def test_a_call_whose_master_goes_away_before_answering_fails():
    m, _, ml = await started()

    async def stuck(args):
        await asyncio.Event().wait()
    m.peers[0].handlers["stuck"] = stuck
    call = asyncio.ensure_future(ml.call("stuck"))
    await asyncio.sleep(0.01)
    m.kill()
    with pytest.raises(Unavailable, match="the master went away before it answered"):
        await asyncio.wait_for(call, STEP)
    await ml.close()


async def test_kept_notifications_wait_in_a_bounded_backlog_and_go_first():
    m, net, ml = await started(backlog=3)
    assert ml.notify("note", n=0) is True
    await until(lambda: m.notes(), "the first note")
    m.kill()
    await until(lambda: not ml.available, "the master seen away")
    net.on_sleep = lambda n: None              # stays away until the notes are queued
    for n in range(1, 6):
        assert ml.notify("note", keep=True, n=n) is False
    assert ml.notify("note", n=99) is False    # not kept: dropped
    assert ml.dropped == 2
    m.up = True
    await m.next_register()
    await until(lambda: ml.available, "available again")
    ml.notify("note", n=6)
    await until(lambda: len(m.notes()) == 5, "the notes")
    assert [a["n"] for a in m.notes()] == [0, 3, 4, 5, 6]
    kinds = [k for k, _ in m.events]
    assert kinds == ["register", "note", "register", "note", "note", "note", "note"]
    await ml.close()


async def test_calls_wait_until_the_answer_is_obeyed():
    obeyed = asyncio.Event()
    seen = []

    async def obey(answer):
        seen.append(answer)
        if len(seen) == 2:
            await obeyed.wait()
    m, _, ml = await started(on_registered=obey)
    m.kill(stay_down=False)
    await m.next_register()
    call = asyncio.ensure_future(ml.call("echo", x=1))
    await asyncio.sleep(0.02)
    assert not call.done() and not ml.available
    obeyed.set()
    assert await asyncio.wait_for(call, STEP) == {"x": 1}
    assert seen[1] == {"tid": 7, "resumed": True, "drop_containers": [3]}
    await ml.close()


async def test_a_refused_first_registration_fails_start_and_a_later_refusal_is_retried():
    m = FakeMaster()
    m.refusals = [RequestError("register: kind must be 'robot' or 'container'")]
    with pytest.raises(RequestError, match="kind must be"):
        await link(Net(a=m)).start()
    m, net, ml = await started()
    m.refusals = [RequestError("register: task set 7 is registered already, on another link")]
    m.kill(stay_down=False)
    assert (await m.next_register())["tid"] == 7
    await until(lambda: ml.registrations == 2, "registered again")
    assert len(net.delays) == 1
    await ml.close()


async def test_close_fails_start_and_waiting_calls_at_once():
    m = FakeMaster()
    m.up = False
    net = Net(a=m)
    ml = link(net, master_wait=60)
    net.real = True
    starting = asyncio.ensure_future(ml.start())
    call = asyncio.ensure_future(ml.call("echo"))
    await asyncio.sleep(0.05)
    await ml.close()
    with pytest.raises(Unavailable, match="closed before it registered"):
        await asyncio.wait_for(starting, STEP)
    with pytest.raises(Unavailable, match="closed"):
        await asyncio.wait_for(call, STEP)
    assert not ml.available


async def test_unless_stopped():
    stopped = asyncio.Event()
    assert await unless_stopped(asyncio.sleep(0, "done"), stopped) == "done"
    never = asyncio.Event()
    waiting = asyncio.ensure_future(unless_stopped(never.wait(), stopped))
    await asyncio.sleep(0.01)
    stopped.set()
    assert await asyncio.wait_for(waiting, STEP) is None


# -- over loopback TCP ------------------------------------------------------------------------------------------
async def test_over_tcp_the_link_finds_a_master_restarted_on_the_same_port():
    registers: asyncio.Queue = asyncio.Queue()
    peers: list[RpcPeer] = []

    async def accept(reader, writer):
        async def register(args):
            registers.put_nowait(args)
            return {"tid": 5}
        await respond(reader, writer, KEY)
        peers.append(RpcPeer(reader, writer, {"register": register}, name="task set").start())

    server = await asyncio.start_server(accept, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    ml = MasterLink(parse_masters(f"127.0.0.1:{port}"), {}, INFO, report=lambda: {"containers": []}, cluster_key=KEY,
                    backoff=Backoff(initial=0.01, cap=0.1))
    await ml.start()
    assert await asyncio.wait_for(registers.get(), STEP) == INFO
    server.close()                             # the master dies: no listener, its links reset
    for p in peers:
        await p.close()
    await server.wait_closed()
    await until(lambda: ml.attempts >= 3, "dials to a master that is down")
    server = await asyncio.start_server(accept, "127.0.0.1", port)
    t0 = time.monotonic()
    assert await asyncio.wait_for(registers.get(), STEP) == {**INFO, "tid": 5, "containers": []}
    assert time.monotonic() - t0 < 0.1 + 0.5          # within the backoff cap (and some slack)
    await until(lambda: ml.available, "available again")
    await ml.close()
    server.close()
    await server.wait_closed()
