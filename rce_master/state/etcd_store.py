"""The master's state in etcd (``rce-master --store etcd://...``): the replicated
:class:`~rce_master.state.store.Store` that several masters share, one leading and the others standing
by (docs/INTERNALS.md, "Several masters"; the election is :mod:`rce_master.leadership.election`).

Layout under the prefix (default ``/rce/``): the record at store key ``k`` is the etcd key
``PREFIX records/`` + ``k`` as a JSON array of strings, its value the record's JSON text; the
leader key is ``PREFIX leader``.

How the synchronous ``Store`` meets a networked store:

- **Reads come from memory.** The store keeps every record's JSON text in memory, as read from
  etcd and changed since (it is a :class:`MemoryStore`); :meth:`get` and :meth:`items` never wait
  on the network, so :class:`~rce_master.state.master_state.MasterState` stays synchronous and sans I/O.
- **The leader writes behind, in order.** :meth:`commit` checks the batch, applies it to memory
  and queues it; one writer task sends the queued batches one at a time, in commit order, each
  as one etcd transaction (all or nothing). :meth:`flush` returns once the batches committed so
  far are in etcd; the master awaits it before it answers a request, so what a task set, a robot
  or an operator was told is in etcd.
- **Fencing.** Each transaction compares the leader key's create revision with this master's
  (:attr:`fence`, from its election): a master whose lease has ended (its key is gone, or is
  another master's now) writes nothing. Its transaction fails and the store fails for good:
  later commits and flushes raise :class:`NotLeader`, :attr:`failed` is set, and the master exits
  (:mod:`rce_master.leadership.elected`).
- **No endpoint answers:** the batch is sent again after a backoff, for as long as the master
  leads (its election ends that within the lease's TTL). A batch that landed but whose answer was
  lost lands again unchanged: puts and deletes of whole records.
- **Bounds.** At most ``max_pending`` batches wait (a commit beyond is refused with
  :class:`Unavailable`); a record larger than one request (:data:`~rce_master.leadership.etcd.MAX_REQUEST_BYTES`)
  is refused with :class:`RequestError`; both before anything changes, and counted
  (:attr:`refused`). A batch of more than ``max_txn_ops`` changes (etcd's ``--max-txn-ops``) or
  bytes than one request takes is written as several transactions, in order (counted:
  :attr:`split`): refusing it would refuse a robot that leaves with many interfaces, or a
  takeover of many task sets. A leader that dies between them leaves part of the batch in etcd;
  such large batches forget things (a robot, a host, a container's interfaces), and the task
  sets' reports complete them when they re-register.
- **Standing by.** :meth:`follow` watches the records and applies each change another master
  writes to memory, calling ``on_change(key, old, new)`` (:meth:`MasterState.apply`): a standby
  serves login and admin reads from the leader's state. Its commits raise :class:`NotLeader`.
  :meth:`lead` makes it the writer: it stops following, reads everything again and writes from
  then on, fenced by its leader key.
"""
from __future__ import annotations

import asyncio
import json
from collections import deque
from collections.abc import Callable

from rce.plumbing.errors import ConfigError, NotLeader, RCEError, RequestError, Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_master.leadership.etcd import (DEFAULT_MAX_TXN_OPS, DEFAULT_PREFIX, MAX_REQUEST_BYTES, Compacted, EtcdClient,
                             EtcdRefused, EtcdUnavailable, b64, range_end, revision)
from rce_master.state.store import Key, MemoryStore, stage

log = get_logger("rce.master.etcd")

RECORDS = "records/"             # under the prefix: the records
LEADER = "leader"                # under the prefix: the leader key (rce_master.leadership.election)
MAX_PENDING = 1024               # batches committed but not yet in etcd; a commit beyond is refused
LOAD_PAGE = 1000                 # records per range request when reading everything
RETRY_MIN, RETRY_MAX = 0.05, 0.5  # s, backoff of a write or a watch that found no endpoint
FOLLOW_IDLE = 10.0               # s, a standby opens its watch again after this long without news: a silent
#                                  network looks like a quiet cluster
CLOSE_FLUSH_TIMEOUT = 2.0        # s, a leader that stops waits this long for its last batches to reach etcd
TXN_OVERHEAD = 4 * 1024          # bytes, a transaction's size beyond its keys and values (compare, JSON)

OnChange = Callable[[Key, "dict | None", "dict | None"], None]


class EtcdStore(MemoryStore):
    """The records under ``prefix`` in the etcd cluster of ``client``, as the module says.

    Build it, then ``await`` :meth:`load`; then :meth:`follow` (a standby) or :meth:`lead`."""

    def __init__(self, client: EtcdClient, prefix: str = DEFAULT_PREFIX, *,
                 max_txn_ops: int = DEFAULT_MAX_TXN_OPS, max_pending: int = MAX_PENDING):
        super().__init__()
        self.client, self.prefix = client, prefix
        self.max_txn_ops, self.max_pending = max_txn_ops, max_pending
        self._records = (prefix + RECORDS).encode()
        self.leader_key = (prefix + LEADER).encode()
        self.revision = 0              # the etcd revision of the last change in memory
        self.fence: int | None = None  # create revision of this master's leader key while it leads
        self.failure: RCEError | None = None
        self.failed = asyncio.Event()  # set when the store failed for good (fenced off, refused)
        self.refused = self.retries = self.written = self.skipped = self.split = 0   # counters
        self._pending: deque[tuple[int, list[list[dict]]]] = deque()   # (seq, its transactions' ops) not in etcd
        self._committed = self._durable = 0                             # seq of the last batch committed, written
        self._waiters: deque[tuple[int, asyncio.Future]] = deque()      # flushes, by the seq they wait for
        self._wake = asyncio.Event()
        self._following: asyncio.Task | None = None
        self.tasks = Tasks("etcd-store")

    @property
    def pending(self) -> int:
        """Batches committed and not yet in etcd."""
        return len(self._pending)

    # -- keys --------------------------------------------------------------------------------------------
    def etcd_key(self, key: Key) -> bytes:
        """The etcd key of store key ``key``."""
        return self._records + json.dumps([str(k) for k in key], separators=(",", ":")).encode()

    def store_key(self, etcd_key: bytes) -> Key:
        """The store key of an etcd key under the records. Raises :class:`ConfigError` naming it
        when it is not one this store writes."""
        try:
            key = json.loads(etcd_key[len(self._records):])
            if isinstance(key, list) and key and all(isinstance(k, str) for k in key):
                return tuple(key)
        except ValueError:
            pass
        raise ConfigError(f"etcd key {etcd_key!r} under {self.prefix}{RECORDS} is not an rce record key")

    # -- writing (the leader) -------------------------------------------------------------------------
    def commit(self, changes) -> None:
        """Apply the batch in memory and queue it for etcd, as the module says. Raises
        :class:`NotLeader` unless this master leads, :class:`RequestError` for a record larger than
        one request, :class:`Unavailable` when too many batches wait; then nothing changed."""
        staged = stage(changes)
        if not staged:
            return
        if self.failure is not None or self.fence is None:
            self.refused += 1
            raise self.failure or NotLeader("this master stands by: only the leader changes the state")
        if len(self._pending) >= self.max_pending:
            self.refused += 1
            raise Unavailable(f"etcd is not keeping up: {len(self._pending)} changes of the state wait to be written")
        txns = self._transactions(staged)
        self._apply_texts(staged)
        self._committed += 1
        self.split += len(txns) > 1
        self._pending.append((self._committed, txns))
        self._wake.set()

    def _transactions(self, staged: list[tuple[Key, str | None]]) -> list[list[dict]]:
        """The batch's puts and deletes as transactions' ops: one transaction when it fits in
        ``max_txn_ops`` operations and one request, else several, in order. Raises
        :class:`RequestError` (counted) for a record larger than one request."""
        txns: list[list[dict]] = [[]]
        size = TXN_OVERHEAD
        for key, text in staged:
            k = b64(self.etcd_key(key))
            op = {"request_put": {"key": k, "value": b64(text)}} if text is not None else \
                {"request_delete_range": {"key": k}}
            n = len(json.dumps(op))
            if TXN_OVERHEAD + n > MAX_REQUEST_BYTES:
                self.refused += 1
                raise RequestError(f"record {'/'.join(key)} is too large for etcd: {n} bytes in a request of at "
                                   f"most {MAX_REQUEST_BYTES}")
            if len(txns[-1]) >= self.max_txn_ops or size + n > MAX_REQUEST_BYTES:
                txns.append([])
                size = TXN_OVERHEAD
            txns[-1].append(op)
            size += n
        return txns

    async def flush(self) -> None:
        """Return once every batch committed so far is in etcd. Raises the store's failure
        (:class:`NotLeader`, :class:`Unavailable`) when it fails first."""
        if self.failure is not None:
            raise self.failure
        if self._durable >= self._committed:
            return
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append((self._committed, fut))
        await fut

    async def _writer(self) -> None:
        """Send the queued batches to etcd, one transaction each, in order (a task of :meth:`lead`)."""
        while self.failure is None:
            await self._wake.wait()
            self._wake.clear()
            while self._pending and self.failure is None:
                seq, txns = self._pending[0]
                while txns:
                    if not await self._write(txns[0]):
                        return
                    txns.pop(0)
                self._pending.popleft()
                self.written += 1
                self._durable = seq
                while self._waiters and self._waiters[0][0] <= seq:
                    fut = self._waiters.popleft()[1]
                    if not fut.done():
                        fut.set_result(None)

    async def _write(self, ops: list[dict]) -> bool:
        """One batch as one transaction fenced by the leader key; False when the store failed."""
        fence = [{"key": b64(self.leader_key), "target": "CREATE", "result": "EQUAL",
                  "create_revision": str(self.fence)}]
        delay = RETRY_MIN
        while True:
            try:
                answer = await self.client.txn(fence, ops)
            except EtcdUnavailable as e:
                self.retries += 1
                log.warning("etcd write waits", reason=e.message, retry_in=delay)
                await asyncio.sleep(delay)
                delay = min(2 * delay, RETRY_MAX)
                continue
            except EtcdRefused as e:
                self.fail(Unavailable(f"etcd refused a change of the state ({e.message}): this master stops leading"))
                return False
            if not answer["succeeded"]:
                self.fail(NotLeader("this master's leadership has ended (its leader key is gone or another "
                                    "master's): its changes are fenced off"))
                return False
            self.revision = revision(answer)
            return True

    def fail(self, error: RCEError) -> None:
        """The store fails for good with ``error``: waiting flushes and later commits raise it."""
        if self.failure is not None:
            return
        self.failure = error
        self.fence = None
        log.error("the state in etcd can no longer be written", reason=error.message, unwritten=len(self._pending))
        self._pending.clear()
        while self._waiters:
            fut = self._waiters.popleft()[1]
            if not fut.done():
                fut.set_exception(error)
        self.failed.set()

    # -- reading everything, following, leading -------------------------------------------------------
    async def load(self, on_change: OnChange | None = None) -> int:
        """Read every record from etcd (one consistent revision, in pages of :data:`LOAD_PAGE`)
        into memory, replacing what was there; each record that differs goes to ``on_change(key,
        old, new)``. Returns the revision. Raises :class:`EtcdUnavailable`, or :class:`ConfigError`
        for a key under the records that is not a store key."""
        end, start, at = range_end(self._records), self._records, 0
        texts: dict[Key, str] = {}
        while True:
            rev, kvs, more = await self.client.range(start, end, limit=LOAD_PAGE, at=at)
            at = at or rev
            for x in kvs:
                texts[self.store_key(x["key"])] = x["value"].decode()
            if not more or not kvs:
                break
            start = kvs[-1]["key"] + b"\0"
        old, self._data, self.revision = self._data, texts, at
        if on_change is not None:
            for key in [k for k in old if k not in texts]:
                on_change(key, json.loads(old[key]), None)
            for key, text in texts.items():
                if old.get(key) != text:
                    on_change(key, _record(old.get(key)), json.loads(text))
        return at

    def follow(self, on_change: OnChange) -> None:
        """Stand by: apply every change of the records in etcd after :attr:`revision` to memory
        and to ``on_change``, until :meth:`lead` or :meth:`aclose`."""
        self._following = self.tasks.spawn(self._follow(on_change), name="follow")

    async def _follow(self, on_change: OnChange) -> None:
        delay = RETRY_MIN
        while True:
            try:
                async for answer in self.client.watch(self._records, range_end(self._records), self.revision + 1,
                                                      idle=FOLLOW_IDLE):
                    for ev in answer["events"]:
                        self._followed(ev, on_change)
                    delay = RETRY_MIN
            except Compacted as e:
                log.warning("the standby reads the state again", reason=e.message)
                await self.load(on_change)
            except EtcdUnavailable as e:
                log.warning("the standby lost its watch on etcd", reason=e.message, retry_in=delay)
                await asyncio.sleep(delay)
                delay = min(2 * delay, RETRY_MAX)

    def _followed(self, ev: dict, on_change: OnChange) -> None:
        """Apply one watch event (``PUT`` or ``DELETE`` of a record) to memory and ``on_change``."""
        x = ev["kv"]
        self.revision = max(self.revision, x["mod_revision"])
        try:
            key = self.store_key(x["key"])
            old = self._data.get(key)
            new = None if ev["type"] == "DELETE" else x["value"].decode()
            if new == old:
                return
            if new is None:
                self._data.pop(key, None)
            else:
                self._data[key] = new
            on_change(key, _record(old), _record(new))
        except (RCEError, ValueError, KeyError, TypeError) as e:
            self.skipped += 1
            log.error("a change in etcd could not be followed", key=x["key"].decode(errors="replace"), reason=str(e))

    async def stop_following(self) -> None:
        """Stop :meth:`follow` (and wait until it has stopped)."""
        task, self._following = self._following, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def lead(self, fence: int, on_change: OnChange | None = None) -> None:
        """Become the writer: stop following, read everything again (changes to ``on_change``),
        and write from now on, fenced by the leader key of create revision ``fence``."""
        await self.stop_following()
        await self.load(on_change)
        self.fence = fence
        self.tasks.spawn(self._writer(), name="writer")

    async def aclose(self, timeout: float = CLOSE_FLUSH_TIMEOUT) -> None:
        """Stop: a leader first waits up to ``timeout`` s for its last batches to reach etcd."""
        if self.fence is not None and self.failure is None and self._pending:
            try:
                async with asyncio.timeout(timeout):
                    await self.flush()
            except (RCEError, TimeoutError) as e:
                log.warning("the last changes did not reach etcd", unwritten=len(self._pending), reason=str(e))
        await self.tasks.cancel_all()


def _record(text: str | None) -> dict | None:
    return None if text is None else json.loads(text)
