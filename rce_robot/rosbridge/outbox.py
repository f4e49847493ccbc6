"""What one rosbridge session sends its client: messages, each the list of websocket frames it goes
as (one JSON text; ``fragment`` ops when it is longer than the ``fragment_size`` the client asked for,
:mod:`rce_robot.rosbridge.fragments`; one binary CBOR frame). A message goes whole or not at all.

The policy is the RCE session's, in the same code (:class:`rce.protocol.lane_queue.LaneQueues`, an
:class:`rce.protocol.outbox.Outbox` per lane, docs/INTERNALS.md "A peer that does not keep up", docs/lanes.md):
ops go out by lane, control (statuses, service calls and responses) before state before bulk (a
subscription's lane: its ``lane`` field, else from its type), with a minimum share for the lower
lanes, all on the client's one websocket; a subscription's ``publish`` ops are topic data
that keep each subscription's newest (past the bound, the oldest of the busiest subscription is
dropped, counted; one older than ``max_lag`` with a newer one behind it is dropped when its turn
comes); other ops (statuses, service calls and responses) are never dropped, and a client that lets
``CONTROL_BACKLOG`` x the bound of them wait does not read (:attr:`RosbridgeOutbox.overrun`).
"""
from __future__ import annotations

import asyncio
import time
from typing import Any

from rce.protocol import jsontext
from rce.protocol.lane_queue import LaneQueues
from rce.interfaces.lanes import Lane
from rce.protocol.robot_outbox import CONTROL_BACKLOG
from rce_robot.rosbridge.fragments import fragment

OUTBOX_SIZE = 256          # publish ops waiting for the client's websocket; past it the busiest subscription's
                           # oldest is dropped (counted)
Frame = str | bytes        # a text (JSON) or binary (CBOR) websocket message


class RosbridgeOutbox:
    """The frames for one client's websocket (:attr:`queue`: :class:`~rce.protocol.lane_queue.LaneQueues` of
    lists of :data:`Frame`, ``size`` data messages at most in each lane). Counters: :attr:`sent` (messages queued),
    :attr:`dropped` (publish ops dropped, for the bound or their age), :attr:`fragments` (``fragment``
    ops queued); :attr:`overrun`: why the client counts as not reading, once it does (else None)."""

    def __init__(self, size: int = OUTBOX_SIZE, max_lag: float | None = None):
        self.queue: LaneQueues[list[Frame]] = LaneQueues(size, max_lag)
        self.sent = self.fragments = self._n = 0
        self.overrun: str | None = None
        self._ready = asyncio.Event()

    @property
    def dropped(self) -> int:
        """Publish ops dropped (each lane's :class:`~rce.protocol.outbox.Outbox`)."""
        return self.queue.dropped

    def put(self, frames: list[Frame], key: Any = None, lane: Lane = Lane.STATE) -> bool:
        """Queue one message's frames: topic data of ``key`` (a subscription) in ``lane``, else an op never
        dropped, in the control lane. Returns True."""
        now = time.monotonic()
        if key is None:
            self.queue.put(frames, now)
            if self.queue.control > CONTROL_BACKLOG * self.queue.queue_size and self.overrun is None:
                self.overrun = f"the rosbridge client does not read: {len(self.queue)} messages wait for it"
        else:
            self.queue.put_data(key, frames, now, lane)
        self.sent += 1
        self._ready.set()
        return True

    def op(self, op: dict, fragment_size: int | None = None, key: Any = None, lane: Lane = Lane.STATE) -> bool:
        """Queue ``op`` as JSON text (``key``, ``lane``: as :meth:`put`); in ``fragment`` ops of at most
        ``fragment_size`` characters of it when it is longer (their ``id``: the op's ``id``, else one
        made up for it). Returns True."""
        text = jsontext.dumps(op)
        if fragment_size is None or len(text) <= fragment_size:
            return self.put([text], key, lane)
        self._n += 1
        frames: list[Frame] = list(fragment(text, fragment_size, str(op.get("id") or f"{op.get('op')}:{self._n}")))
        self.fragments += len(frames)
        return self.put(frames, key, lane)

    def get_nowait(self) -> list[Frame]:
        """The next message's frames (asyncio.QueueEmpty when none waits)."""
        got = self.queue.take(time.monotonic())
        if got is None:
            raise asyncio.QueueEmpty
        lane, frames = got
        self.queue.sent(lane, sum(len(f) for f in frames))
        return frames

    async def get(self) -> list[Frame]:
        """The next message's frames, once one waits."""
        while True:
            try:
                return self.get_nowait()
            except asyncio.QueueEmpty:
                self._ready.clear()
                await self._ready.wait()

    def empty(self) -> bool:
        return len(self.queue) == 0
