"""Login hardening (docs/SECURITY.md, "Login"): the master's password check behind the robot
endpoints' and rosbridge's handshakes (the ``auth`` op).

- :class:`LoginGuard` (sans-I/O): failed logins are counted per user name *from one address* and per
  address (any user names); past the free failures each further one doubles a back-off, during which
  attempts are refused with :class:`~rce.plumbing.errors.Throttled` (HTTP 429 with ``Retry-After``) before any
  password is checked. An attempt counts as failed as it starts (so that many at once cannot slip
  through) and is taken back when it succeeds; a success forgets the user's failures from that
  address. At most a few checks per address run at once; the next ones from that address *wait*
  for them (a fleet's robots behind one NAT logging in together all get in, a few at a time),
  bounded in number and time, and are then checked against the back-off like any other. Unknown
  user names count as any other, so throttling tells nothing about which exist.
  A user is not locked out everywhere: a user's failures from one address do not hold back the
  same user logging in from another (else anyone could lock any user out).
- :class:`PasswordCheck`: runs scrypt (:func:`rce_master.auth.users.verify`) in a few threads
  (``hashlib.scrypt`` releases the GIL), never on the event loop, with a bounded number waiting, and
  at most a few at a time per address: past the bound an attempt is refused at once (429), so that
  an attack cannot queue without bound ahead of real logins. A login that has no
  failure counted against its user and address (a real robot's, usually) goes ahead of the others in
  the queue (:mod:`rce_master.auth.scrypt_pool`), and the last few places are kept for such logins.

Tables are bounded (:data:`MAX_TRACKED` entries each, the least recently failed forgotten first,
counted) and forget an entry :data:`FAILURE_MEMORY` s after its last failure, at a cost of O(expired).
"""
from __future__ import annotations

import asyncio
import math
import time
from collections import OrderedDict
from dataclasses import dataclass

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from rce.plumbing.errors import AuthError, Throttled
from rce_master.state.model import User
from rce_master.auth.scrypt_pool import NORMAL, URGENT, PriorityPool
from rce_master.auth.users import verify

FAILURES_PER_USER = 5           # failed logins of one user name from one address before it backs off (a typo or two
#                                 and a retry stay free); rce-master --login-failures-per-user
FAILURES_PER_ADDRESS = 20       # failed logins from one address, any user names, before it backs off (a NAT of a few
#                                 robots); rce-master --login-failures-per-address
BACKOFF_FIRST = 1.0             # s, the back-off after the last free failure; it doubles with each further one ...
BACKOFF_MAX = 300.0             # s ... up to this (rce-master --login-backoff-max): 5 min, about 12 guesses an hour
FAILURE_MEMORY = 900.0          # s after its last failure a user's or address's count is forgotten (15 min)
MAX_TRACKED = 10_000            # entries per table (user@address, address): ~1 MB; past it the least recently
#                                 failed entry is forgotten (counted in rce_master_login_guard_evicted)
SCRYPT_WORKERS = 2              # threads that run scrypt (~50 ms each): the master's share of a small machine
SCRYPT_QUEUE = 16               # password checks that may wait for a thread; past it: 429 at once (a wait of at most
#                                 16 x 50 ms / 2 = 0.4 s for a real login behind an attack)
MAX_IN_FLIGHT_PER_ADDRESS = 2   # password checks one address may have running or waiting at once: one address
#                                 cannot fill the queue; more attempts from it wait (below)
ADDRESS_WAITERS = 1024          # attempts waiting for their address's checks to end, all addresses together (a fleet
#                                 behind one NAT logging in at once); past it: 429 at once
ADDRESS_WAIT = 30.0             # s an attempt waits for its address's checks before 429 (1000 robots' logins at
#                                 2 x 50 ms per 2 checks take 25 s)
RESERVED_FOR_CLEAN = 4          # places of the queue kept for logins with no failure counted against their user
#                                 and address: an attack from many addresses cannot fill the whole queue
BUSY_RETRY_AFTER = 1.0          # s, Retry-After when the queue is full or an address has its checks in flight


@dataclass
class _Entry:
    failures: int = 0
    until: float = 0.0          # monotonic s: attempts before it are refused
    last: float = 0.0           # monotonic s of the last counted failure


class FailureTable:
    """Failed-login counts by key (a ``(user, address)`` pair or an address), bounded and expiring.

    ``free``: failures before the back-off; the ``k``-th failure past them holds the key back
    ``min(backoff_max, backoff_first * 2**k)`` s."""

    def __init__(self, free: int, *, backoff_first: float = BACKOFF_FIRST, backoff_max: float = BACKOFF_MAX,
                 memory: float = FAILURE_MEMORY, max_entries: int = MAX_TRACKED):
        self.free, self.backoff_first, self.backoff_max = free, backoff_first, backoff_max
        self.memory, self.max_entries = memory, max_entries
        self.entries: OrderedDict[object, _Entry] = OrderedDict()     # least recently failed first
        self.evicted = 0

    def expire(self, now: float) -> None:
        """Forget the entries whose last failure is older than ``memory``: O(expired)."""
        while self.entries:
            key, e = next(iter(self.entries.items()))
            if e.last + self.memory > now or e.until > now:
                return
            del self.entries[key]

    def retry_after(self, key: object, now: float) -> float:
        """s before ``key`` may try again (0: now)."""
        e = self.entries.get(key)
        return max(0.0, e.until - now) if e is not None else 0.0

    def fail(self, key: object, now: float) -> None:
        """Count a failure of ``key`` (its back-off starts once past ``free``)."""
        e = self.entries.pop(key, None) or _Entry()
        e.failures += 1
        e.last = now
        if e.failures >= self.free:
            e.until = now + min(self.backoff_max, self.backoff_first * 2 ** (e.failures - self.free))
        self.entries[key] = e
        while len(self.entries) > self.max_entries:
            self.entries.popitem(last=False)
            self.evicted += 1

    def take_back(self, key: object) -> None:
        """The last counted failure of ``key`` was not one (the attempt succeeded or was not checked)."""
        e = self.entries.get(key)
        if e is None:
            return
        e.failures -= 1
        if e.failures <= 0:
            del self.entries[key]
        elif e.failures < self.free:
            e.until = 0.0

    def forget(self, key: object) -> None:
        self.entries.pop(key, None)


class LoginGuard:
    """Who may try a password now (the module docstring). Sans-I/O: times are given (monotonic s)."""

    def __init__(self, *, per_user: int = FAILURES_PER_USER, per_address: int = FAILURES_PER_ADDRESS,
                 backoff_max: float = BACKOFF_MAX, in_flight_per_address: int = MAX_IN_FLIGHT_PER_ADDRESS):
        self.users = FailureTable(per_user, backoff_max=backoff_max)
        self.addresses = FailureTable(per_address, backoff_max=backoff_max)
        self.in_flight_per_address = in_flight_per_address
        self.in_flight: dict[str, int] = {}

    def admit(self, user: str, addr: str, now: float) -> bool:
        """Let ``user`` from ``addr`` try a password (counted as failed until :meth:`done` says
        otherwise); returns True when it is *clean* (no failure counted against either before).
        Raises :class:`Throttled` (its ``retry_after``, s) while either backs off or ``addr`` has
        its checks in flight."""
        for table in (self.users, self.addresses):
            table.expire(now)
        wait = max(self.users.retry_after((user, addr), now), self.addresses.retry_after(addr, now))
        if wait > 0:
            raise Throttled(f"too many failed logins; retry after {math.ceil(wait)} s", retry_after=math.ceil(wait))
        if not self.has_room(addr):
            raise Throttled(f"this address has {self.in_flight_per_address} logins in progress; retry after "
                            f"{BUSY_RETRY_AFTER:g} s", retry_after=BUSY_RETRY_AFTER)
        clean = (user, addr) not in self.users.entries and addr not in self.addresses.entries
        self.in_flight[addr] = self.in_flight.get(addr, 0) + 1
        self.users.fail((user, addr), now)
        self.addresses.fail(addr, now)
        return clean

    def has_room(self, addr: str) -> bool:
        """Whether ``addr`` has fewer than ``in_flight_per_address`` checks running or waiting."""
        return self.in_flight.get(addr, 0) < self.in_flight_per_address

    def done(self, user: str, addr: str, ok: bool | None) -> None:
        """The attempt :meth:`admit` let through ended: ``ok`` True (the password was right: the
        user's failures from ``addr`` are forgotten), False (wrong: it stays counted) or None (not
        checked: taken back)."""
        left = self.in_flight.get(addr, 1) - 1
        if left > 0:
            self.in_flight[addr] = left
        else:
            self.in_flight.pop(addr, None)
        if ok is True:
            self.users.forget((user, addr))
        elif ok is None:
            self.users.take_back((user, addr))
        if ok is not False:
            self.addresses.take_back(addr)


class PasswordCheck:
    """The master's ``auth``: :class:`LoginGuard`, then scrypt in a bounded pool (the module
    docstring). ``workers`` threads, ``queue`` checks waiting at most, of which ``reserved`` only for
    clean logins (:meth:`LoginGuard.admit`). A Prometheus collector
    (``rce_master_auth`` by result, the guard's tables and the pool's load)."""

    def __init__(self, guard: LoginGuard | None = None, *, workers: int = SCRYPT_WORKERS, queue: int = SCRYPT_QUEUE,
                 reserved: int = RESERVED_FOR_CLEAN, waiters: int = ADDRESS_WAITERS, wait: float = ADDRESS_WAIT):
        self.guard = guard or LoginGuard()
        self.pool = PriorityPool(workers, "scrypt")
        self.bound, self.reserved = workers + queue, reserved
        self.busy = 0                   # checks running or waiting in the pool
        self.max_waiters, self.wait, self.waiting = waiters, wait, 0
        self.room = asyncio.Condition()  # notified when a check ends (an address may have room again)
        self.results = {"ok": 0, "failed": 0, "throttled": 0, "busy": 0}

    async def _wait_for_room(self, addr: str) -> None:
        """Wait until ``addr`` may start a check (:meth:`LoginGuard.has_room`), at most ``wait`` s,
        among at most ``max_waiters``; past either, the next :meth:`LoginGuard.admit` refuses."""
        if self.guard.has_room(addr) or self.waiting >= self.max_waiters:
            return
        self.waiting += 1
        try:
            async with self.room:
                async with asyncio.timeout(self.wait):
                    await self.room.wait_for(lambda: self.guard.has_room(addr))
        except TimeoutError:
            pass
        finally:
            self.waiting -= 1

    async def _check_ended(self) -> None:
        async with self.room:
            self.room.notify_all()

    async def authenticate(self, users: dict[str, User], user: str, digest_hex: str, addr: str) -> None:
        """Check ``digest_hex`` (hex SHA-256 of the password) for ``user`` logging in from ``addr``.
        Raises :class:`AuthError` (the same for an unknown user as for a wrong password) or
        :class:`Throttled` (back-off, or too many checks waiting)."""
        await self._wait_for_room(addr)
        try:
            clean = self.guard.admit(user, addr, time.monotonic())
        except Throttled:
            self.results["throttled"] += 1
            raise
        ok: bool | None = None
        try:
            if self.busy >= self.bound - (0 if clean else self.reserved):
                self.results["busy"] += 1
                raise Throttled(f"too many logins in progress; retry after {BUSY_RETRY_AFTER:g} s",
                                retry_after=BUSY_RETRY_AFTER)
            ok = await self._run(URGENT if clean else NORMAL, users, user, digest_hex)
        finally:
            self.guard.done(user, addr, ok)
            await self._check_ended()
        self.results["ok" if ok else "failed"] += 1
        if not ok:
            raise AuthError(f"invalid user ID or password for user {user!r}")

    async def _run(self, priority: int, users: dict[str, User], user: str, digest_hex: str) -> bool:
        loop = asyncio.get_running_loop()
        self.busy += 1
        fut = self.pool.submit(priority, verify, users, user, digest_hex)
        # the slot is free when scrypt ends, even if the caller gave up waiting for it
        fut.add_done_callback(lambda _f: loop.call_soon_threadsafe(self._release))
        return await asyncio.wrap_future(fut)

    def _release(self) -> None:
        self.busy -= 1

    def close(self) -> None:
        self.pool.close()

    def collect(self):
        """(prometheus_client collector) Login results, guard tables, pool load."""
        c = CounterMetricFamily("rce_master_auth", "Password checks of robot and rosbridge logins, by result "
                                "(throttled: refused by the back-off; busy: refused, too many waiting)",
                                labels=["result"])
        for k, v in self.results.items():
            c.add_metric([k], v)
        yield c
        g = self.guard
        yield GaugeMetricFamily("rce_master_login_guard_tracked", "Entries in the failed-login tables (user@address "
                                "and address)", value=len(g.users.entries) + len(g.addresses.entries))
        yield CounterMetricFamily("rce_master_login_guard_evicted", "Failed-login entries forgotten because a table "
                                  "was full", value=g.users.evicted + g.addresses.evicted)
        yield GaugeMetricFamily("rce_master_auth_pending", "Password checks running or waiting", value=self.busy)
        yield GaugeMetricFamily("rce_master_auth_waiting", "Logins waiting for their address's checks to end",
                                value=self.waiting)
