"""rce_master.state.etcd_store and rce_master.leadership.election on a real etcd on loopback (tests/etcd_server.py).

The store: each batch is one etcd transaction (all its records at one revision, or none), the
state reloads whole in another store, a batch too large or not JSON changes nothing, a standby
refuses to write and follows the leader's writes, writes wait for an unreachable etcd and land
in order, and the queue of unwritten batches has a bound.

The election: one of two masters leads; the other takes over within 5 s when the leader vanishes
without a word (as after kill -9: it renews nothing, revokes nothing) and at once when it
resigns; a deposed leader's writes are fenced off; a leader that cannot reach etcd stops leading
before its lease can expire."""
from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

import pytest

from rce.plumbing.errors import ConfigError, NotLeader, RequestError, Unavailable
from rce_master.leadership.election import LEASE_TTL, Election
from rce_master.leadership.etcd import EtcdClient, parse_url, range_end
from rce_master.state.etcd_store import EtcdStore
from rce_master.state.master_state import MasterState

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from etcd_server import EtcdServer  # noqa: E402
from test_core_store import assert_same, busy_state  # noqa: E402

U = "alice"
TAKEOVER_BOUND = 5.0     # s, the promise: a standby leads within 5 s of the leader's death
WAIT = 10.0              # s, the most a test waits for something that happens in well under a second


@pytest.fixture(scope="module")
def etcd(tmp_path_factory):
    with EtcdServer(tmp_path_factory.mktemp("etcd")) as e:
        yield e


@pytest.fixture
def prefix(request) -> str:
    """A key prefix of this test's own (the tests share one etcd)."""
    return f"/t/{request.node.name}/"


@pytest.fixture
async def clients(etcd):
    """Clients of the etcd, closed after the test: ``clients()`` makes one (timeout 0.5 s)."""
    made: list[EtcdClient] = []

    def make() -> EtcdClient:
        made.append(EtcdClient([etcd.endpoint], timeout=0.5))
        return made[-1]
    yield make
    for c in made:
        await c.close()


async def leader(client: EtcdClient, prefix: str, name: str, **kw) -> tuple[Election, EtcdStore]:
    """An elected master's election and its store, leading."""
    election = Election(client, prefix, {"control": f"{name}:1", "http": f"http://{name}:2/"}, **kw)
    store = EtcdStore(client, prefix)
    await store.load()
    await store.lead(await asyncio.wait_for(election.campaign(), WAIT))
    return election, store


async def until(pred, timeout: float = WAIT) -> float:
    """Wait until ``pred()`` holds (polling every 10 ms); the seconds it took."""
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not met in time"
        await asyncio.sleep(0.01)
    return time.monotonic() - t0


async def abandon(election: Election, store: EtcdStore | None = None) -> None:
    """What etcd sees of a master killed with SIGKILL: no renewal, no revocation, no write."""
    await election.tasks.cancel_all()
    if store is not None:
        await store.tasks.cancel_all()


# -- the store ---------------------------------------------------------------------------------------
def test_store_url():
    assert parse_url("etcd://h1:2379,h2:2380") == parse_url("etcd://h1:2379,h2:2380/")
    u = parse_url("etcd://h1:2379,10.0.0.2:2380/fleet/a?max-txn-ops=1000")
    assert u.endpoints == ("http://h1:2379", "http://10.0.0.2:2380") and u.prefix == "/fleet/a/"
    assert u.max_txn_ops == 1000 and parse_url("etcd://h:1").prefix == "/rce/"
    for bad, why in (("http://h:1", "expected etcd://"), ("etcd://h", "'h' is not HOST:PORT"),
                     ("etcd://h:1?x=2", "unknown option"), ("etcd://h:1?max-txn-ops=1", "integer >= 2")):
        with pytest.raises(ConfigError, match=why):
            parse_url(bad)


async def test_a_batch_is_one_transaction_and_the_state_reloads_whole(clients, prefix):
    client = clients()
    _, store = await leader(client, prefix, "a")
    records = list(busy_state().store.items())
    store.commit(records)                                         # one batch
    s = MasterState(store)
    s.set_param(U, "c1", "/speed", 0.7)                           # two more, one record each
    s.delete_param("bob", "c1", "cfg")
    await store.flush()
    assert store.written == 3 and store.pending == 0
    records_prefix = (prefix + "records/").encode()
    rev, kvs, _ = await client.range(records_prefix, range_end(records_prefix))
    assert len(kvs) == len(records) - 1
    assert len({x["mod_revision"] for x in kvs}) == 2             # the first batch's records share one revision
    again = EtcdStore(clients(), prefix)
    assert await again.load() == rev
    assert dict(again.items()) == dict(store.items())
    assert_same(s, MasterState(again))


async def test_a_record_too_large_or_not_json_changes_nothing(clients, prefix):
    _, store = await leader(clients(), prefix, "a")
    store.commit([(("user", U), {"name": U})])
    with pytest.raises(RequestError, match="record param/alice/c/p is too large for etcd"):
        store.commit([(("user", U), None), (("param", U, "c", "p"), {"v": "x" * 2_000_000})])
    with pytest.raises(RequestError, match="record param/alice/c/p is not JSON"):
        store.commit([(("user", U), None), (("param", U, "c", "p"), {"v": float("nan")})])
    assert dict(store.items()) == {("user", U): {"name": U}} and store.pending <= 1 and store.refused == 1
    await store.flush()
    again = EtcdStore(clients(), prefix)
    await again.load()
    assert dict(again.items()) == {("user", U): {"name": U}}


async def test_a_batch_larger_than_a_transaction_is_written_as_several_in_order(clients, prefix):
    client = clients()
    _, store = await leader(client, prefix, "a")
    store.max_txn_ops = 3
    store.commit([(("user", f"u{i}"), {"name": f"u{i}"}) for i in range(7)] + [(("user", "u0"), None)])
    await store.flush()
    assert store.split == 1 and store.written == 1
    records = (prefix + "records/").encode()
    _, kvs, _ = await client.range(records, range_end(records))
    assert len({x["mod_revision"] for x in kvs}) == 3                      # 3 + 3 + 2 operations
    assert [x["key"][len(records):] for x in kvs] == [f'["user","u{i}"]'.encode() for i in range(1, 7)]


async def test_a_standby_refuses_to_write_and_follows_the_leader(clients, prefix):
    _, store = await leader(clients(), prefix, "a")
    standby = EtcdStore(clients(), prefix)
    await standby.load()
    with pytest.raises(NotLeader, match="stands by"):
        standby.commit([(("user", U), {"name": U})])
    s = MasterState(standby)
    seen = []
    standby.follow(lambda k, old, new: (seen.append((k, old, new)), s.followed(k, old, new)))
    leading = MasterState(store)
    leading.add_user(U, "pw")
    leading.register_taskset("container", "ch", "h", {})
    c, _ = leading.add_container(U, "r1", "c1", {"memory": 64})
    leading.container_ready(c, "tcp://x:1", "unconfined")
    leading.remove_container(U, "c1")
    await store.flush()
    await until(lambda: standby.revision == store.revision)
    assert_same(leading, s)
    assert [(k, old is None, new is None) for k, old, new in seen if k[0] == "container"] == \
        [(("container", U, "c1"), True, False), (("container", U, "c1"), False, False),
         (("container", U, "c1"), False, True)]
    await standby.stop_following()


async def test_writes_wait_for_an_unreachable_etcd_and_land_in_order(etcd, clients, prefix):
    _, store = await leader(clients(), prefix, "a")
    etcd.pause()
    try:
        for i in range(5):
            store.commit([(("counter", "n"), {"next": i})])
        flushed = asyncio.ensure_future(store.flush())
        await until(lambda: store.retries >= 1)
        assert not flushed.done() and store.pending == 5
    finally:
        etcd.resume()
    await asyncio.wait_for(flushed, WAIT)
    again = EtcdStore(clients(), prefix)
    await again.load()
    assert again.get(("counter", "n")) == {"next": 4} and store.written == 5


async def test_the_batches_waiting_for_etcd_are_bounded(etcd, clients, prefix):
    _, store = await leader(clients(), prefix, "a")
    store.max_pending = 2
    etcd.pause()
    try:
        store.commit([(("user", "a"), {"name": "a"})])
        store.commit([(("user", "b"), {"name": "b"})])
        with pytest.raises(Unavailable, match="etcd is not keeping up: 2 changes"):
            store.commit([(("user", "c"), {"name": "c"})])
        assert store.get(("user", "c")) is None and store.refused == 1
    finally:
        etcd.resume()
    await asyncio.wait_for(store.flush(), WAIT)
    store.commit([(("user", "c"), {"name": "c"})])
    await store.flush()


# -- the election --------------------------------------------------------------------------------------
async def test_one_leads_and_the_other_takes_over_when_it_vanishes(clients, prefix):
    a, store_a = await leader(clients(), prefix, "a")
    MasterState(store_a).add_user(U, "pw")
    await store_a.flush()
    b = Election(clients(), prefix, {"control": "b:1", "http": "http://b:2/"})
    campaign = asyncio.ensure_future(b.campaign())
    await until(lambda: b.leader is not None)
    assert b.leader == a.me and not b.elected and a.elected and not campaign.done()
    t0 = time.monotonic()
    await abandon(a, store_a)                       # kill -9
    fence = await asyncio.wait_for(campaign, TAKEOVER_BOUND)
    took = time.monotonic() - t0
    assert b.elected and b.leader == b.me and fence > a.fence
    assert took < TAKEOVER_BOUND and took > LEASE_TTL / 3      # it waited for the lease, not for nothing
    store_b = EtcdStore(b.client, prefix)
    await store_b.lead(fence)
    assert store_b.get(("user", U)) is not None
    await b.resign()


async def test_a_leader_that_resigns_is_replaced_at_once(clients, prefix):
    a, _ = await leader(clients(), prefix, "a")
    b = Election(clients(), prefix, {"control": "b:1"})
    campaign = asyncio.ensure_future(b.campaign())
    await until(lambda: b.leader is not None)
    t0 = time.monotonic()
    await a.resign()
    await asyncio.wait_for(campaign, WAIT)
    assert time.monotonic() - t0 < LEASE_TTL / 2
    await b.resign()


async def test_a_deposed_leaders_writes_are_fenced_off(clients, prefix):
    a, store_a = await leader(clients(), prefix, "a")
    store_a.commit([(("user", U), {"name": U})])
    await store_a.flush()
    await clients().lease_revoke(a.lease)           # its lease ends behind its back (a partition, a long pause)
    b, store_b = await leader(clients(), prefix, "b")
    store_a.commit([(("user", U), None), (("user", "mallory"), {"name": "mallory"})])
    with pytest.raises(NotLeader, match="fenced off"):
        await asyncio.wait_for(store_a.flush(), WAIT)
    assert store_a.failed.is_set()
    with pytest.raises(NotLeader, match="fenced off"):
        store_a.commit([(("user", "eve"), {"name": "eve"})])
    await asyncio.wait_for(a.lost.wait(), WAIT)      # its next renewal hears the lease is gone
    assert not a.elected and "expired" in a.why_lost
    again = EtcdStore(clients(), prefix)
    await again.load()
    assert dict(again.items()) == {("user", U): {"name": U}}
    assert b.elected and store_b.failure is None
    await b.resign()


async def test_a_leader_cut_off_from_etcd_stops_leading_before_its_lease_ends(etcd, clients, prefix):
    a, _ = await leader(clients(), prefix, "a")
    etcd.pause()
    try:
        t0 = time.monotonic()
        await asyncio.wait_for(a.lost.wait(), WAIT)
        took = time.monotonic() - t0
    finally:
        etcd.resume()
    assert took < LEASE_TTL and "not renewed" in a.why_lost
