"""The life of one of several masters on etcd (``rce-master --store etcd://...``; docs/INTERNALS.md,
"Several masters").

1. Read the state from etcd (:meth:`EtcdStore.load`) and stand by: serve login and admin reads
   from it while following the leader's writes (:meth:`EtcdStore.follow`); refuse ``register``
   and admin writes with :class:`~rce.plumbing.errors.NotLeader`, naming the leader.
2. Campaign (:meth:`Election.campaign`). Once elected: read the state again and write from then
   on, fenced (:meth:`EtcdStore.lead`), and take office (:meth:`Master.take_office`): the task
   sets in the state are absent until they re-register here, as after a restart.
3. Run until a stop signal: then write the last changes, close, and resign (the lease is revoked,
   so a standby leads at once). Or until this master stops leading (its lease could not be
   renewed, or a write was fenced off): then it closes every link at once and exits with status 1,
   to be started again (as a standby) by its supervisor. A deposed leader never acts again, as
   Kubernetes' controller manager and scheduler do when they lose their lease.
"""
from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from rce.plumbing.errors import NotLeader, RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_master.leadership.election import Election
from rce_master.leadership.etcd import EtcdClient, parse_url
from rce_master.state.etcd_store import EtcdStore
from rce_master.server import Master

log = get_logger("rce.master")


class ElectedOffice:
    """The :class:`~rce_master.leadership.office.Office` of a master on etcd: it leads once it is elected
    and has taken office (in between, requests are still refused), and while its lease lasts."""

    def __init__(self, election: Election):
        self.election = election
        self.in_office = False
        self.settled = asyncio.Event()     # set once this master leads, or once it knows another does

    @property
    def leading(self) -> bool:
        return self.in_office and self.election.elected

    @property
    def leader(self) -> dict | None:
        return self.election.leader

    @property
    def me(self) -> dict:
        return self.election.me


async def run(url: str, make_master: Callable[[EtcdStore, ElectedOffice], Master],
              start: Callable[[Master], Awaitable[dict]], ready: Callable[[Master], None],
              stop: asyncio.Event) -> None:
    """Run one master on the etcd cluster of ``url`` (:func:`rce_master.leadership.etcd.parse_url`) until
    ``stop`` is set. ``make_master(store, office)`` builds it; ``start(master)`` starts it listening
    and returns its addresses (``{"control": "HOST:PORT", "http": URL, ...}``, what the leader key
    holds); ``ready(master)`` is called once it leads or knows another master does. Raises
    :class:`NotLeader` when the master stopped leading (the process exits 1), and
    :class:`Unavailable` when etcd cannot be read at start."""
    cfg = parse_url(url)
    client = EtcdClient(cfg.endpoints)
    tasks = Tasks("rce-master-office")
    try:
        store = EtcdStore(client, cfg.prefix, max_txn_ops=cfg.max_txn_ops)
        await store.load()
        election = Election(client, cfg.prefix)
        office = ElectedOffice(election)
        master = make_master(store, office)
        election.me = await start(master)
        store.follow(master.state.followed)
        tasks.spawn(_lead(master, store, office), name="campaign")
        if await _first(tasks, office.settled, election.standing_by, stop, election.lost, store.failed) in (0, 1):
            ready(master)
            await _first(tasks, stop, election.lost, store.failed)
        if stop.is_set():
            await _step_down(master, store, election)
            return
        office.in_office = False                   # stop acting now, then close everything
        why = election.why_lost or (store.failure.message if store.failure else "?")
        store.fail(NotLeader(f"this master stopped leading: {why}"))
        await master.stop()
        await store.aclose()
        raise NotLeader(f"this master stopped leading ({why}); it exits: start it again and it stands by")
    finally:
        await tasks.cancel_all()
        await client.close()


async def _first(tasks: Tasks, *events: asyncio.Event) -> int:
    """Wait until one of ``events`` is set; the index of the first that is."""
    waits = [tasks.spawn(e.wait(), name="wait") for e in events]
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for w in waits:
            w.cancel()
    return next(i for i, e in enumerate(events) if e.is_set())


async def _lead(master: Master, store: EtcdStore, office: ElectedOffice) -> None:
    """Campaign; once elected, read the state again, write from now on, and take office."""
    fence = await office.election.campaign()
    try:
        await store.lead(fence, master.state.followed)
        office.in_office = True
        master.take_office()
        office.settled.set()
    except RCEError as e:
        store.fail(Unavailable(f"the elected master could not take office: {e.message}"))


async def _step_down(master: Master, store: EtcdStore, election: Election) -> None:
    """A clean stop: close the links, write the last changes, and resign (a standby leads at once)."""
    log.info("master stopping", leading=election.elected)
    await master.stop()
    await store.aclose()
    await election.resign()
