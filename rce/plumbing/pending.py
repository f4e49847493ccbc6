"""The one table of calls waiting for a reply: a fresh id per call, its future, its timeout,
settle and fail-all.

Every request/response exchange in rce uses it: control-plane requests (:mod:`rce.transport.rpc`),
service calls on the data plane and the container bus, a robot's replies to calls from
the cloud, and the client library's service calls and barriers. Sans I/O: it never
sends anything; the caller sends the request between :meth:`PendingCalls.open` and
:meth:`PendingCalls.wait`.

::

    calls = PendingCalls("master")
    cid = calls.open()
    link.send({"id": cid, ...})
    result = await calls.wait(cid, timeout=30.0)     # Timeout after 30 s
    ...
    calls.settle(cid, result)                        # from the read loop
"""
from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable, Hashable, Iterator
from typing import Any

from rce.plumbing.errors import RCEError, Timeout, Unavailable


class PendingCalls:
    """Calls in flight, keyed by id. ``name`` names the peer in error messages.

    Ids are ints from 1 (:meth:`open`), or any hashable the caller picks
    (:meth:`open` with ``key``, e.g. a protocol's 32-hex-char msgID)."""

    def __init__(self, name: str, ids: Callable[[], Hashable] | None = None):
        self.name = name
        self._next = ids or itertools.count(1).__next__
        self._calls: dict[Hashable, asyncio.Future] = {}
        self._info: dict[Hashable, Any] = {}
        self.closed: RCEError | None = None

    def __len__(self) -> int:
        return len(self._calls)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._calls

    def open(self, key: Hashable | None = None, info: Any = None) -> Hashable:
        """Register a new call; returns its id (``key`` when given). ``info`` is kept with it
        (:meth:`info`, :meth:`items`). Raises the error the table was closed with
        (:meth:`fail_all`), and :class:`RCEError` for an id already in flight."""
        if self.closed is not None:
            raise type(self.closed)(self.closed.message)
        cid = self._next() if key is None else key
        if cid in self._calls:
            raise RCEError(f"call id {cid!r} to {self.name} is already in flight")
        self._calls[cid] = asyncio.get_running_loop().create_future()
        self._info[cid] = info
        return cid

    async def wait(self, cid: Hashable, timeout: float | None, what: str = "the call") -> Any:
        """Wait for call ``cid`` to be settled; returns its result and forgets it.

        Raises :class:`Timeout` after ``timeout`` s (None: no limit), or the error it was
        failed with (:meth:`fail`, :meth:`fail_all`)."""
        fut = self._calls.get(cid)
        if fut is None:
            raise RCEError(f"no call {cid!r} to {self.name} in flight")
        deadline = asyncio.timeout(timeout)     # not wait_for: on 3.11 it can swallow a cancellation
        try:
            async with deadline:
                return await fut
        except TimeoutError:
            if deadline.expired():
                raise Timeout(f"{self.name} did not answer {what} within {timeout:g} s") from None
            raise                               # the call itself failed with a timeout from further away
        finally:
            self.forget(cid)

    async def call(self, send: Callable[[Hashable], Any], timeout: float | None, what: str = "the call",
                   key: Hashable | None = None) -> Any:
        """Open a call, ``send(cid)`` the request, and wait for the answer (:meth:`wait`).
        An exception from ``send`` (e.g. a full link) forgets the call and propagates."""
        cid = self.open(key)
        try:
            send(cid)
        except BaseException:
            self.forget(cid)
            raise
        return await self.wait(cid, timeout, what)

    def settle(self, cid: Hashable, result: Any) -> bool:
        """Complete call ``cid`` with ``result``. False when no such call waits (late, unknown)."""
        fut = self._calls.get(cid)
        if fut is None or fut.done():
            return False
        fut.set_result(result)
        return True

    def fail(self, cid: Hashable, error: BaseException) -> bool:
        """Complete call ``cid`` with ``error``. False when no such call waits."""
        fut = self._calls.get(cid)
        if fut is None or fut.done():
            return False
        fut.set_exception(error)
        return True

    def fail_all(self, error: RCEError | None = None, *, close: bool = True) -> int:
        """Fail every waiting call with ``error`` (default: :class:`Unavailable`, link closed);
        with ``close`` (the default) later :meth:`open` calls raise it too. Returns how many."""
        error = error or Unavailable(f"the link to {self.name} closed")
        if close:
            self.closed = error
        n = 0
        for fut in self._calls.values():
            if not fut.done():
                fut.set_exception(type(error)(error.message))
                n += 1
        return n

    def forget(self, cid: Hashable) -> None:
        """Drop call ``cid`` (its waiter, if any, is cancelled)."""
        fut = self._calls.pop(cid, None)
        self._info.pop(cid, None)
        if fut is not None and not fut.done():
            fut.cancel()

    def info(self, cid: Hashable) -> Any:
        """The ``info`` given to :meth:`open` for ``cid`` (None if unknown)."""
        return self._info.get(cid)

    def items(self) -> Iterator[tuple[Hashable, Any]]:
        """``(id, info)`` of every call in flight (a snapshot)."""
        return iter(list(self._info.items()))
