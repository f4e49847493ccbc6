"""The election of one leader among masters on etcd (docs/INTERNALS.md, "Several masters"): etcd's
lease-and-key recipe (clientv3 ``concurrency.Election``,
https://etcd.io/docs/v3.4/dev-guide/api_concurrency_reference_v3/), with one leader key.

- Each master holds a lease of :data:`LEASE_TTL` s and renews it every :data:`KEEPALIVE_INTERVAL` s.
- **Campaign**: one transaction creates ``PREFIX leader`` = this master's addresses (:attr:`Election.me`),
  bound to its lease, only if the key is absent (create revision 0). The master whose transaction
  succeeds leads; the key's create revision is its *fence*: every write of the state compares it
  (:mod:`rce_master.state.etcd_store`), so a master that no longer leads writes nothing.
- **Standing by**: the others read the leader's addresses from the key (:attr:`Election.leader`, named
  in their refusals), watch it, and campaign again when it goes: when the leader's lease ends
  (kill -9: at most :data:`LEASE_TTL` after its last renewal, plus etcd's expiry check) or when it
  resigns (revokes its lease on a clean stop: at once). A standby reads the key again at least
  every :data:`RECHECK` s even when its watch says nothing.
- **Stepping down**: a leader that has not renewed its lease for :data:`STEP_DOWN_AFTER` s stops
  leading (:attr:`Election.lost` is set; the master exits, :mod:`rce_master.leadership.elected`). etcd lets a
  lease expire no earlier than its TTL after the last renewal that reached it, which is after the
  last renewal the leader sent; so the old leader has stopped before a new one can be elected, as
  long as both clocks run at about the same rate. Its writes are fenced whatever the clocks do.
"""
from __future__ import annotations

import asyncio
import json
import time

from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_master.leadership.etcd import Compacted, EtcdClient, EtcdRefused, EtcdUnavailable, b64, kv, revision
from rce_master.state.etcd_store import LEADER, RETRY_MAX, RETRY_MIN

log = get_logger("rce.master.election")

LEASE_TTL = 2                          # s, the leader lease: a leader killed with SIGKILL is replaced after about
#                                        this long (2 s is etcd's minimum with its default --election-timeout)
KEEPALIVE_INTERVAL = LEASE_TTL / 3     # s between renewals (and the timeout of one): two may fail in a row
STEP_DOWN_AFTER = LEASE_TTL * 2 / 3    # s without a renewal after which a leader stops leading, LEASE_TTL / 3
#                                        before etcd may let its lease expire
RECHECK = 5.0                          # s, a standby reads the leader key at least this often (a silent network)


class Election:
    """This master's part in the election under ``prefix`` of ``client``'s cluster, as the module says.

    ``me`` is what the leader key holds while this master leads (``{"control": "HOST:PORT",
    "http": "http://HOST:PORT/", "name", "pid"}``); :attr:`leader` is the leader's (None: none
    known), :attr:`elected` whether this master won and holds its lease, :attr:`fence` its leader
    key's create revision."""

    def __init__(self, client: EtcdClient, prefix: str, me: dict | None = None, *, ttl: int = LEASE_TTL,
                 keepalive_interval: float = KEEPALIVE_INTERVAL, step_down_after: float = STEP_DOWN_AFTER,
                 recheck: float = RECHECK):
        self.client = client
        self.key = (prefix + LEADER).encode()
        self.me: dict = dict(me or {})
        self.ttl, self.keepalive_interval, self.step_down_after, self.recheck = (ttl, keepalive_interval,
                                                                                 step_down_after, recheck)
        self.elected = False
        self.leader: dict | None = None
        self.fence = 0
        self.lease = 0                     # this master's lease id (0: none now)
        self.lost = asyncio.Event()        # set when this master led and stopped leading
        self.standing_by = asyncio.Event() # set once a campaign found another master leading
        self.why_lost = ""
        self.tasks = Tasks("election")

    async def campaign(self) -> int:
        """Stand by until this master leads; returns its fence. Retries while etcd is unreachable."""
        delay = RETRY_MIN
        while True:
            try:
                if not self.lease:
                    await self._grant()
                won, held, rev = await self._try()
                if won:
                    log.info("this master leads", fence=self.fence, lease=self.lease)
                    return self.fence
                if held:
                    await self._watch(rev)
                delay = RETRY_MIN
            except Compacted:                   # the revision read is gone already: read the key again
                continue
            except EtcdUnavailable as e:
                log.warning("the election waits for etcd", reason=e.message, retry_in=delay)
                await asyncio.sleep(delay)
                delay = min(2 * delay, RETRY_MAX)
            except EtcdRefused as e:            # our lease has expired meanwhile (standing by on a slow network)
                log.warning("the election starts over with a new lease", reason=e.message)
                self.lease = 0

    async def _grant(self) -> None:
        lease = await self.client.lease_grant(self.ttl)
        self.lease = lease
        self.tasks.spawn(self._keep(lease, time.monotonic()), name=f"keepalive-{lease}")

    async def _try(self) -> tuple[bool, bool, int]:
        """One transaction: create the leader key if absent, else read it. ``(won, held by
        another, revision)``."""
        key = b64(self.key)
        answer = await self.client.txn(
            [{"key": key, "target": "CREATE", "result": "EQUAL", "create_revision": "0"}],
            [{"request_put": {"key": key, "value": b64(json.dumps(self.me)), "lease": str(self.lease)}}],
            [{"request_range": {"key": key}}])
        rev = revision(answer)
        if answer["succeeded"]:
            return self._won(rev), False, rev
        kvs = [kv(x) for x in (answer["responses"][0].get("response_range") or {}).get("kvs", [])]
        if not kvs:                                # gone between the compare and now: try again
            self.leader = None
            return False, False, rev
        if kvs[0]["lease"] == self.lease:          # an earlier try landed, its answer was lost
            return self._won(kvs[0]["create_revision"]), False, rev
        self.leader = _leader(kvs[0]["value"])
        self.standing_by.set()
        return False, True, rev

    def _won(self, fence: int) -> bool:
        self.elected, self.fence, self.leader = True, fence, dict(self.me)
        return True

    async def _watch(self, rev: int) -> None:
        """Wait until the leader key goes (or :attr:`recheck` s pass), following its value meanwhile."""
        async for answer in self.client.watch(self.key, None, rev + 1, idle=self.recheck):
            for ev in answer["events"]:
                if ev["type"] == "DELETE":
                    self.leader = None
                    return
                self.leader = _leader(ev["kv"]["value"])

    async def _keep(self, lease: int, granted: float) -> None:
        """Renew ``lease`` every :attr:`keepalive_interval` s until it ends (see the module)."""
        last_ok = granted
        while True:
            sent = time.monotonic()
            try:
                ttl = await self.client.lease_keepalive(lease, timeout=self.keepalive_interval)
            except EtcdUnavailable:
                ttl = None
            if ttl == 0:
                self._lease_ended(lease, "etcd says its lease has expired")
                return
            if ttl:
                last_ok = sent
            elif time.monotonic() - last_ok >= self.step_down_after:
                self._lease_ended(lease, f"its lease was not renewed for {self.step_down_after:g} s (etcd unreachable)")
                return
            await asyncio.sleep(max(0.0, sent + self.keepalive_interval - time.monotonic()))

    def _lease_ended(self, lease: int, why: str) -> None:
        if lease != self.lease:
            return
        self.lease = 0
        if self.elected:
            self.elected, self.leader, self.why_lost = False, None, why
            log.error("this master stops leading", reason=why)
            self.lost.set()
        else:
            log.warning("a standby's lease ended; it takes a new one", reason=why)

    async def resign(self) -> None:
        """Stop renewing and revoke the lease (a clean stop): the leader key goes at once and a
        standby leads without waiting for the lease to expire. Quiet when etcd is unreachable."""
        await self.tasks.cancel_all()
        lease, self.lease, self.elected = self.lease, 0, False
        if lease:
            try:
                await self.client.lease_revoke(lease)
            except RCEError as e:
                log.warning("could not revoke the lease", reason=e.message)


def _leader(value: bytes) -> dict | None:
    """The leader's addresses in the leader key's value (None when it is not a JSON object)."""
    try:
        d = json.loads(value)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None
