"""A few threads that run blocking calls (the master's scrypt checks, :mod:`rce_master.auth.login_guard`)
in order of priority, then of arrival: a real robot's login waits behind no attack's guesses.

``hashlib.scrypt`` releases the GIL, so the threads run beside the event loop. The pool does not
bound what waits: its one caller does (:class:`~rce_master.auth.login_guard.PasswordCheck`)."""
from __future__ import annotations

import itertools
import queue
import threading
from concurrent.futures import Future
from typing import Any, Callable

URGENT, NORMAL = 0, 1       # priorities: lower runs first
STOP = 2                    # the stop marks of close(), after every call


class PriorityPool:
    """``workers`` daemon threads named ``name-N``, taking calls from one priority queue."""

    def __init__(self, workers: int, name: str):
        self._queue: queue.PriorityQueue = queue.PriorityQueue()
        self._seq = itertools.count()
        self._closed = False
        self._threads = [threading.Thread(target=self._work, name=f"{name}-{i}", daemon=True) for i in range(workers)]
        for t in self._threads:
            t.start()

    def submit(self, priority: int, fn: Callable[..., Any], *args: Any) -> Future:
        """Run ``fn(*args)`` in a thread once the calls of lower ``priority`` number (and earlier ones
        of the same) have started; its result or exception comes in the returned future."""
        fut: Future = Future()
        self._queue.put((priority, next(self._seq), fn, args, fut))
        return fut

    def close(self) -> None:
        """Stop the threads once they finish their current call; calls still queued are cancelled."""
        self._closed = True
        for _ in self._threads:
            self._queue.put((STOP, next(self._seq), None, (), None))   # after everything queued

    def _work(self) -> None:
        while True:
            _, _, fn, args, fut = self._queue.get()
            if fn is None:
                return
            if self._closed or not fut.set_running_or_notify_cancel():
                fut.cancel()
                continue
            try:
                fut.set_result(fn(*args))
            except BaseException as e:       # handed to the waiting caller
                fut.set_exception(e)
