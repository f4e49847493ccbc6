"""Big text frames are parsed off the event loop, in a worker process, so that a hostile
robot's huge frame cannot stall every other session.

``json.loads`` holds the GIL for the whole parse (a 30 MiB frame of numbers: about 0.25 s, one of
small objects: seconds), so a thread would not free the loop: a big frame that holds many values
(:data:`MANY_VALUES`: building them is the cost; one long string parses faster on the loop than on
its trip to a worker and back) goes to a process (:class:`concurrent.futures.ProcessPoolExecutor`,
``spawn`` start method: no fork of a running loop), which runs
:func:`rce.protocol.frames.parse_frame` (depth limit, parse, binary part ids) and sends the message
back pickled. Its robot's later frames wait for it (the robot's order is kept); every other robot's
frames go on. The message still comes back as objects built under the GIL (unpickled): measured on
a loaded 2-core host, the loop's longest stall while parsing a 30 MiB frame of numbers fell from
about 0.9 s to 0.2-0.5 s, not to nothing. At most :data:`PARSE_QUEUE` big frames are parsed or
waiting at once, all robots together; beyond that a robot's reading pauses until a slot is free
(the websocket's own read-ahead bound then holds the rest)."""
from __future__ import annotations

import asyncio
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from rce.plumbing.errors import ProtocolError
from rce.plumbing.log import get_logger
from rce.protocol.frames import parse_frame

log = get_logger("rce.robot")

BIG_FRAME = 256 * 1024   # chars of a text frame above which it may be parsed in a worker: below, the parse
                         # costs the loop a few ms at most
MANY_VALUES = 20_000     # commas (about JSON values) above which a big frame goes to the worker: a frame of few
                         # values (one long string) parses at C speed, faster than its trip to a worker and back
PARSE_WORKERS = 1        # worker processes; one core stays the loop's (2-core hosts)
PARSE_QUEUE = 4          # big frames parsed or waiting for a worker at once, all robots together


def _parse(text: str) -> tuple[dict, list[str]] | ProtocolError:
    """(in the worker) :func:`parse_frame`, its refusal returned rather than raised."""
    try:
        return parse_frame(text)
    except ProtocolError as e:
        return e


class ParsePool:
    """Parses text frames longer than ``threshold`` chars in ``workers`` processes, ``queue`` at once.
    :attr:`parsed`: big frames parsed so far; the workers start with the first big frame."""

    def __init__(self, threshold: int = BIG_FRAME, workers: int = PARSE_WORKERS, queue: int = PARSE_QUEUE):
        self.threshold, self.workers = threshold, workers
        self._slots = asyncio.Semaphore(queue)
        self._pool: ProcessPoolExecutor | None = None
        self.parsed = 0

    def takes(self, frame: str | bytes) -> bool:
        """Is ``frame`` a text frame this pool parses: longer than the threshold, with many values?"""
        return isinstance(frame, str) and len(frame) > self.threshold and frame.count(",") > MANY_VALUES

    async def parse(self, text: str) -> tuple[dict, list[str]] | ProtocolError:
        """``(message, binary part ids)`` of JSON frame ``text``, or the :class:`ProtocolError` that
        says why it was refused (:func:`parse_frame`). A worker that died is replaced."""
        async with self._slots:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"))
            try:
                result = await asyncio.get_running_loop().run_in_executor(self._pool, _parse, text)
            except BrokenProcessPool:
                log.warning("a frame parser process died; starting another")
                broken, self._pool = self._pool, None
                broken.shutdown(wait=False)
                return ProtocolError(f"text frame of {len(text)} chars could not be parsed (its parser died)")
            self.parsed += 1
            return result

    def close(self) -> None:
        """Stop the workers (a parse in progress is abandoned)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
