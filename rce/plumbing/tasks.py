"""Tasks that are kept: every task the engine starts is referenced until it ends, and its
failure is logged, never lost (asyncio keeps only a weak reference to a task: one kept by
nobody can be garbage-collected mid-run; ruff's RUF006).

::

    tasks = Tasks("robot-endpoint")
    tasks.spawn(self._writer(), name="writer")
    ...
    await tasks.cancel_all()
"""
from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any

from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger

log = get_logger("rce.tasks")


class Tasks:
    """A set of running tasks owned by one object (a session, a link, a server).

    ``owner`` names it in logs. A task that raises is logged at WARNING (an
    :class:`RCEError`: its message) or ERROR (anything else: with the traceback);
    cancellation is normal and not logged."""

    def __init__(self, owner: str):
        self.owner = owner
        self._tasks: set[asyncio.Task] = set()
        self.failed = 0

    def __len__(self) -> int:
        return len(self._tasks)

    def spawn(self, coro: Coroutine[Any, Any, Any], name: str | None = None) -> asyncio.Task:
        """Start ``coro`` as a task that is kept until it ends; returns the task."""
        task = asyncio.get_running_loop().create_task(coro, name=f"{self.owner}:{name}" if name else None)
        self._tasks.add(task)
        task.add_done_callback(self._done)
        return task

    def _done(self, task: asyncio.Task) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            return
        e = task.exception()
        if e is None:
            return
        self.failed += 1
        if isinstance(e, RCEError):
            log.warning("task failed", owner=self.owner, task=task.get_name(), reason=e.message)
        else:
            log.error("task failed", owner=self.owner, task=task.get_name(), exc_info=e)

    async def wait_all(self) -> None:
        """Wait until every task has ended, those spawned meanwhile too (the current task is spared)."""
        me = asyncio.current_task()
        while tasks := [t for t in self._tasks if t is not me]:
            await asyncio.gather(*tasks, return_exceptions=True)

    async def cancel_all(self) -> None:
        """Cancel every task and wait until they have ended (the current task is spared)."""
        me = asyncio.current_task()
        tasks = [t for t in self._tasks if t is not me]
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)
