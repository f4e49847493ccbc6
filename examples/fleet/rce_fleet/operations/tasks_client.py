"""The operators' side of the task API: an RCE client's channel to the fleet's tasks.

:class:`TaskChannel` adds, on a logged-in :class:`rce_client.connection.Connection`, three
interface pairs to the fleet container and connects them (tags prefixed with the client's
robotID, so any number of clients can attach):

===========================  ==========================  ==============================
container side               client side                 topic, class
===========================  ==========================  ==============================
``<id>_taskIn``  PubIf       ``<id>_task`` SubConv       /fleet/task  fleet/Task
``<id>_cancelIn`` PubIf      ``<id>_cancel`` SubConv     /fleet/task_cancel fleet/TaskCancel
``<id>_tasksOut`` SubIf      ``<id>_tasks`` PubConv      /fleet/tasks fleet/TaskList
===========================  ==========================  ==============================

:meth:`TaskChannel.add` and :meth:`TaskChannel.cancel` send a request and wait for the
global planner's answer (``fleet/TaskAnswer`` in ``/fleet/tasks``); a refusal raises
:class:`TaskRefused` with its code and reason. The fleet manager, ``rce-fleet task`` and the
HTTP API (:mod:`rce_fleet.live.webui`) all go through it.
"""
from __future__ import annotations

import asyncio
import itertools
import os
import re
from typing import Callable

from rce.plumbing.errors import RCEError, Unavailable

__all__ = ["ANSWER_TIMEOUT_S", "TaskChannel", "TaskRefused"]

ANSWER_TIMEOUT_S = 10.0     # s a request waits for the planner's answer
SETUP_TIMEOUT_S = 30.0      # s for the channel's interfaces to come up
CLOSE_TIMEOUT_S = 5.0       # s the cloud gets to remove the container-side interfaces


class TaskRefused(RCEError):
    """The fleet refused a task request: ``code`` (bad_request, not_found, conflict, timeout)
    and the reason."""

    def __init__(self, code: str, reason: str):
        super().__init__(reason)
        self.code, self.reason = code, reason


class TaskChannel:
    """See the module docstring. ``conn``: a logged-in connection whose robotID is
    ``robot_id``; ``ctag``: the fleet container; ``on_tasks(list_dict)`` sees every
    ``/fleet/tasks``; ``latest`` keeps the newest."""

    def __init__(self, conn, robot_id: str, ctag: str, source: str = "",
                 on_tasks: Callable[[dict], None] | None = None):
        self.conn, self.robot_id, self.ctag = conn, robot_id, ctag
        self.source = source or robot_id
        self.on_tasks = on_tasks
        self.latest: dict | None = None
        p = re.sub(r"[^A-Za-z0-9_]", "_", robot_id)
        self.tags = {k: f"{p}_{k}" for k in ("task", "cancel", "tasks", "taskIn", "cancelIn", "tasksOut")}
        self._pub = self._cancel_pub = None
        self._answers: dict[str, dict] = {}
        self._event = asyncio.Event()
        self._ids = itertools.count(1)
        self._prefix = f"{p}-{os.getpid()}-{id(self) & 0xffff:x}"

    def _links(self) -> list[tuple[str, str, str, str, str, str]]:
        t = self.tags
        return [(t["taskIn"], "PublisherInterface", t["task"], "SubscriberConverter", "fleet/Task", "/fleet/task"),
                (t["cancelIn"], "PublisherInterface", t["cancel"], "SubscriberConverter", "fleet/TaskCancel",
                 "/fleet/task_cancel"),
                (t["tasksOut"], "SubscriberInterface", t["tasks"], "PublisherConverter", "fleet/TaskList",
                 "/fleet/tasks")]

    async def attach(self, timeout: float = SETUP_TIMEOUT_S) -> None:
        """Add and connect the interfaces; returns once they are up and the first
        ``/fleet/tasks`` arrived. Raises :class:`Unavailable` with the cloud's reason."""
        c = self.conn
        errors: list[str] = []
        c.on_error(errors.append)
        adds, links = [], []
        for ctag_i, ctype, mine, mtype, cls, topic in self._links():
            adds += [{"endpointTag": self.ctag, "interfaceTag": ctag_i, "interfaceType": ctype, "className": cls,
                      "addr": topic},
                     {"endpointTag": self.robot_id, "interfaceTag": mine, "interfaceType": mtype, "className": cls}]
            links.append({"tagA": f"{self.ctag}/{ctag_i}", "tagB": f"{self.robot_id}/{mine}"})
        c.subscriber(self.tags["tasks"], "fleet/TaskList", self._on_list)
        self._pub = c.publisher(self.tags["task"], "fleet/Task")
        self._cancel_pub = c.publisher(self.tags["cancel"], "fleet/TaskCancel")
        await c.configure({"addInterfaces": adds})
        await c.send("CX", {"connect": links})
        await c.barrier(timeout)
        if errors:
            raise Unavailable(f"cannot attach to the fleet's tasks in container {self.ctag!r}: {errors[0]}")
        await c.wait_interfaces_up([self.tags[k] for k in ("task", "cancel", "tasks")], timeout)
        await self.wait_list(lambda _m: True, timeout)

    async def detach(self) -> None:
        """Remove the container-side interfaces (the cloud removes the client's own at logout)."""
        try:
            await self.conn.configure({"removeInterfaces": [{"endpointTag": self.ctag, "interfaceTag": t}
                                                            for t, *_ in self._links()]})
            await self.conn.barrier(CLOSE_TIMEOUT_S)
        except RCEError:
            pass

    def _on_list(self, msg) -> None:
        if not isinstance(msg, dict):
            return
        self.latest = msg
        for a in msg.get("answers", []):
            if a.get("request", "").startswith(self._prefix):
                self._answers[a["request"]] = a
        self._event.set()
        if self.on_tasks:
            self.on_tasks(msg)

    async def wait_list(self, pred: Callable[[dict], bool], timeout: float = ANSWER_TIMEOUT_S) -> dict:
        """The first ``/fleet/tasks`` (current or later) for which ``pred`` holds; raises
        :class:`Unavailable` after ``timeout`` s."""
        loop = asyncio.get_running_loop()
        end = loop.time() + timeout
        while self.latest is None or not pred(self.latest):
            left = end - loop.time()
            if left <= 0:
                raise Unavailable(f"no fleet task list within {timeout:g} s (is the fleet's global planner up?)")
            self._event.clear()
            try:
                async with asyncio.timeout(left):
                    await self._event.wait()
            except TimeoutError:
                pass
        return self.latest

    async def _ask(self, pub, msg: dict, timeout: float) -> dict:
        req = msg["request"] = f"{self._prefix}-{next(self._ids)}"
        await pub.publish(msg)
        try:
            await self.wait_list(lambda _m: req in self._answers, timeout)
        except Unavailable:
            raise TaskRefused("timeout", f"no answer from the fleet within {timeout:g} s") from None
        a = self._answers.pop(req)
        if not a.get("ok"):
            raise TaskRefused(a.get("code") or "bad_request", a.get("error", "refused"))
        return a

    async def add(self, errands: list, *, priority: float = 0.0, earliest_start_s: float = 0.0,
                  deadline_s: float = 0.0, task_id: str = "", timeout: float = ANSWER_TIMEOUT_S,
                  source: str = "") -> dict:
        """Queue a task (errands: cells or place names, in order) on behalf of ``source`` (default: the
        channel's); returns its ``fleet/TaskStatus`` (JSON form). Raises :class:`TaskRefused` with the
        fleet's reason."""
        a = await self._ask(self._pub, {"id": task_id, "errands": [str(e) for e in errands],
                                        "priority": float(priority), "earliest_start_s": float(earliest_start_s),
                                        "deadline_s": float(deadline_s), "source": source or self.source}, timeout)
        return self.get(a["id"]) or {"id": a["id"], "state": "queued"}

    async def cancel(self, task_id: str, timeout: float = ANSWER_TIMEOUT_S, source: str = "") -> dict:
        """Cancel task ``task_id`` on behalf of ``source`` (default: the channel's; the task's
        ``cancelled_by``); returns its status. Raises :class:`TaskRefused` (not_found, conflict: already
        closed)."""
        a = await self._ask(self._cancel_pub, {"id": str(task_id), "source": source or self.source}, timeout)
        return self.get(a["id"]) or {"id": a["id"], "state": "cancelled"}

    def tasks(self) -> list[dict]:
        """The tasks of the newest ``/fleet/tasks``: open ones, then recently closed ones."""
        return list((self.latest or {}).get("tasks", []))

    def get(self, task_id: str) -> dict | None:
        """Task ``task_id`` of the newest list (None: not in it)."""
        return next((t for t in self.tasks() if t.get("id") == task_id), None)
