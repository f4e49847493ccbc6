"""What one rosbridge session sends its client: a bounded queue of messages, each the list of
websocket frames it goes as (one JSON text; ``fragment`` ops when it is longer than the
``fragment_size`` the client asked for, :mod:`rce_robot.rosbridge_fragments`; one binary CBOR
frame). A message goes whole or not at all: when the queue is full it is dropped and counted.
"""
from __future__ import annotations

import asyncio

from rce.protocol import jsontext
from rce_robot.rosbridge_fragments import fragment

OUTBOX_SIZE = 256          # messages waiting for the client's websocket; past it a message is dropped (counted)
Frame = str | bytes        # a text (JSON) or binary (CBOR) websocket message


class Outbox:
    """The frames for one client's websocket (``queue``: lists of :data:`Frame`, at most
    ``size`` messages). Counters: :attr:`sent` (messages queued), :attr:`dropped` (messages
    thrown away: queue full), :attr:`fragments` (``fragment`` ops queued)."""

    def __init__(self, size: int = OUTBOX_SIZE):
        self.queue: asyncio.Queue[list[Frame]] = asyncio.Queue(size)
        self.sent = self.dropped = self.fragments = self._n = 0

    def put(self, frames: list[Frame]) -> bool:
        """Queue one message's frames; False (counted in :attr:`dropped`) when the queue is full."""
        try:
            self.queue.put_nowait(frames)
        except asyncio.QueueFull:
            self.dropped += 1
            return False
        self.sent += 1
        return True

    def op(self, op: dict, fragment_size: int | None = None) -> bool:
        """Queue ``op`` as JSON text; in ``fragment`` ops of at most ``fragment_size`` characters of
        it when it is longer (their ``id``: the op's ``id``, else one made up for it). False: dropped."""
        text = jsontext.dumps(op)
        if fragment_size is None or len(text) <= fragment_size:
            return self.put([text])
        self._n += 1
        frames: list[Frame] = list(fragment(text, fragment_size, str(op.get("id") or f"{op.get('op')}:{self._n}")))
        if self.put(frames):
            self.fragments += len(frames)
            return True
        return False

    def get_nowait(self) -> list[Frame]:
        """The oldest queued message's frames (asyncio.QueueEmpty when none)."""
        return self.queue.get_nowait()

    def empty(self) -> bool:
        return self.queue.empty()
