"""A robot's requests to the master, one at a time and in order, and the DMs held back for them,
sans I/O (the DM ordering rule of docs/INTERNALS.md): a DM for an interface that an earlier request
may create waits until that request is done; once one waits, every later DM waits behind it, so the
robot's order is kept. Both queues are bounded by ``queue_size``; the session refuses what does not fit.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from rce.plumbing.errors import ProtocolError
from rce.protocol.schema import RequestData


@dataclass(slots=True)
class _Held:
    data: dict
    after: int          # the DM waits until this many requests are done


class HoldBack:
    """Requests (``(type, data)``, ``data`` their model) waiting for the master, the one it handles
    (:attr:`in_flight`: its type), and the DMs (their ``data``) that wait for earlier requests.
    ``queue_size``: each queue's bound."""

    def __init__(self, queue_size: int):
        self.queue_size = queue_size
        self.requests: deque[tuple[str, RequestData]] = deque()
        self.in_flight: str | None = None
        self._received = self._done = 0                 # requests taken / answered
        self._held: deque[_Held] = deque()

    @property
    def full(self) -> bool:
        """Do ``queue_size`` requests wait (a new one is refused)?"""
        return len(self.requests) >= self.queue_size

    @property
    def waiting(self) -> int:
        """Requests not yet answered, the one in flight included."""
        return len(self.requests) + (self.in_flight is not None)

    @property
    def held(self) -> int:
        """DMs waiting for earlier requests."""
        return len(self._held)

    def add(self, type_: str, data: RequestData) -> None:
        """A request of the robot's (the caller checked :attr:`full`)."""
        self._received += 1
        self.requests.append((type_, data))

    def next(self) -> tuple[str, RequestData] | None:
        """The request to send to the master now, or None (one is in flight, or none waits)."""
        if self.in_flight is not None or not self.requests:
            return None
        type_, data = self.requests.popleft()
        self.in_flight = type_
        return type_, data

    def done(self) -> tuple[str, list[dict]]:
        """The master answered the request in flight: its type, and the DMs that waited for it, in
        order. Raises :class:`ProtocolError` when none is in flight."""
        if self.in_flight is None:
            raise ProtocolError("request_done with no request in flight")
        type_, self.in_flight = self.in_flight, None
        self._done += 1
        released = []
        while self._held and self._held[0].after <= self._done:
            released.append(self._held.popleft().data)
        return type_, released

    def must_hold(self, known: bool) -> bool:
        """Must a DM wait: DMs wait already, or its interface is not ``known`` while requests are pending?"""
        return bool(self._held) or (not known and self._done < self._received)

    def hold(self, data: dict) -> bool:
        """Hold DM ``data`` until the requests taken so far are done; False when ``queue_size`` wait."""
        if len(self._held) >= self.queue_size:
            return False
        self._held.append(_Held(data, self._received))
        return True
