"""The operators' task API of the live fleet, sans-I/O: requests in, answers and task states out.

:class:`TaskBook` holds every task the fleet was given. It validates the requests that
arrive on ``/fleet/task`` (``fleet/Task``) and ``/fleet/task_cancel`` (``fleet/TaskCancel``)
and answers each one (``fleet/TaskAnswer`` in ``/fleet/tasks``): a refused request changes
nothing and says why, with a code:

- ``bad_request``: no errand, an unknown place, a cell outside the grid, on a wall, blocked
  or cut off from the robots, a bad priority or time window;
- ``conflict``: a task id that exists already, a cancel of a task that is done, failed or
  cancelled;
- ``not_found``: a cancel of a task id the fleet never had.

The open tasks live in a :class:`rce_fleet.lifelong.TaskPool` (its states: queued,
assigned, active, done, failed, cancelled), which the dispatcher
(:mod:`rce_fleet.operations.dispatcher`) hands to the lifelong allocator. Each task also keeps the
fleet time (s, the robots' clock) at which it reached each state, its robot and, when it
failed or was cancelled, the reason. The pool counts in *steps*: one step is ``step_s``
seconds, about the time a robot takes to cross a cell.
"""
from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass
from typing import Callable

from rce.protocol.limits import short_repr

from ..lifelong import Task, TaskPool, TaskState
from .places import PlaceError, Places

__all__ = ["MAX_ERRANDS", "TaskBook", "TaskRecord"]

MAX_ERRANDS = 32            # errands per task
MAX_PRIORITY = 100.0        # |priority| at most
KEEP_CLOSED = 200           # closed tasks kept for look-ups (the oldest are forgotten; counters stay)
SHOW_CLOSED = 50            # closed tasks in each fleet/TaskList
KEEP_ANSWERS = 100          # answers in each fleet/TaskList (the newest)
ID_RE = re.compile(r"^[A-Za-z0-9_.:-]{1,64}$")
MAX_TAG = 128               # characters of a request's ``request`` and ``source`` kept (the rest cut): they are
                            # echoed in every fleet/TaskList, and no answer carries more than a short prefix of input


class Refused(Exception):
    """A request refused: ``code`` (bad_request, not_found, conflict) and the reason."""

    def __init__(self, code: str, text: str):
        super().__init__(text)
        self.code, self.text = code, text


@dataclass
class TaskRecord:
    """One task of the book: what operators gave (string id, errands as given: a place by its name, a cell by
    its number; source: who created it, time window in fleet s, 0: none; ``cancelled_by``: who cancelled it) beside the
    pool's :class:`~rce_fleet.lifelong.Task`, which owns its state: ``state``, ``robot``,
    ``reason``, ``history`` and the fleet time (s) it was ``assigned``, became ``active`` and
    ``finished`` (0 when not (yet) reached)."""

    id: str
    task: Task
    errands: list[str]
    source: str
    created: float
    earliest_start: float = 0.0
    deadline: float = 0.0
    cancelled_by: str = ""

    @property
    def cells(self) -> tuple[int, ...]:
        return self.task.errands

    @property
    def state(self) -> TaskState:
        return self.task.state

    @property
    def open(self) -> bool:
        return self.task.open

    @property
    def robot(self) -> str:
        return self.task.robot

    @property
    def reason(self) -> str:
        return self.task.reason

    @property
    def history(self) -> list[tuple[float, str, str]]:
        """[(fleet time, state, robot)] per transition."""
        return [(at, st, robot) for at, st, _, robot in self.task.history]

    @property
    def assigned(self) -> float:
        return self.task.times.get(TaskState.ASSIGNED.value, 0.0)

    @property
    def active(self) -> float:
        return self.task.times.get(TaskState.ACTIVE.value, 0.0) if self.task.opened else 0.0

    @property
    def finished(self) -> float:
        return 0.0 if self.open else self.task.times[self.state.value]

    def message(self) -> dict:
        """The ``fleet/TaskStatus`` (JSON form)."""
        t = self.task
        return {"id": self.id, "errands": list(self.errands), "cells": list(t.errands), "priority": t.priority,
                "state": self.state.value, "robot": self.robot, "next_errand": t.next_errand, "reason": self.reason,
                "source": self.source, "cancelled_by": self.cancelled_by, "created": self.created,
                "earliest_start": self.earliest_start, "deadline": self.deadline, "assigned": self.assigned,
                "active": self.active,
                "finished": self.finished, "reached": list(t.reached)}


class TaskBook:
    """See the module docstring.

    places: the named places; usable(cell) -> None or why an errand cannot use ``cell`` now
    (blocked, cut off); step_s: seconds per pool step (> 0).
    """

    def __init__(self, places: Places, usable: Callable[[int], str | None] = lambda c: None, step_s: float = 5.0):
        if not step_s > 0:
            raise ValueError("step_s must be > 0")
        self.places, self.usable, self.step_s = places, usable, float(step_s)
        self.pool = TaskPool(keep_closed=KEEP_CLOSED)
        self.records: dict[str, TaskRecord] = {}          # open ones and the newest closed ones
        self.by_pool: dict[int, TaskRecord] = {}          # pool id -> record, open tasks
        self.closed: deque[str] = deque()                 # ids of closed records kept, oldest first
        self.answers: deque[dict] = deque(maxlen=KEEP_ANSWERS)
        self.counts = {s: 0 for s in (TaskState.DONE, TaskState.FAILED, TaskState.CANCELLED)}
        self.deadline_missed = 0
        self.durations: list[float] = []                  # s from creation to done, per done task
        self.changed = True                               # something operators see changed since message()
        self._ids: set[str] = set()
        self._auto = 0

    # -- requests --------------------------------------------------------------------------------
    def request_add(self, req: dict, now: float) -> dict:
        """Answer a ``fleet/Task`` (JSON form) received at fleet time ``now``; queues the task
        when valid. Returns the answer (also kept for ``/fleet/tasks``)."""
        try:
            rec = self._add(req, now)
            return self._answer(req, rec.id, None)
        except Refused as e:
            return self._answer(req, str(req.get("id") or ""), e)

    def request_cancel(self, req: dict, now: float) -> dict:
        """Answer a ``fleet/TaskCancel``: cancel an open task (its robot drops it)."""
        tid = str(req.get("id") or "")
        try:
            rec = self.records.get(tid)
            if rec is None:
                if tid in self._ids:
                    raise Refused("conflict", f"task {tid!r} is closed (long ago)")
                raise Refused("not_found", f"no task {short_repr(tid)}")
            if not rec.open:
                raise Refused("conflict", f"task {tid!r} is {rec.state.value}: it cannot be cancelled")
            rec.cancelled_by = _tag(req.get("source"))
            self.close(rec, TaskState.CANCELLED, f"cancelled by {rec.cancelled_by or 'an operator'}", now)
            return self._answer(req, tid, None)
        except Refused as e:
            return self._answer(req, tid, e)

    def _answer(self, req: dict, tid: str, err: Refused | None) -> dict:
        """The answer to ``req``: it names the task by ``tid`` only when that is a task id (an id that is not,
        a megabyte of text say, is named in the error by its first characters alone)."""
        a = {"request": _tag(req.get("request")), "id": tid if ID_RE.match(tid) else "", "ok": err is None,
             "code": err.code if err else "", "error": err.text if err else ""}
        self.answers.append(a)
        self.changed = True
        return a

    def _add(self, req: dict, now: float) -> TaskRecord:
        tid = str(req.get("id") or "").strip()
        if tid:
            if not ID_RE.match(tid):
                raise Refused("bad_request", f"task id {short_repr(tid)}: use 1-64 letters, digits or _ . : -")
            if tid in self._ids:
                raise Refused("conflict", f"task {tid!r} exists already")
        errands = [str(e).strip() for e in (req.get("errands") or [])]
        if not errands:
            raise Refused("bad_request", "a task needs at least one errand (a cell number or a place name)")
        if len(errands) > MAX_ERRANDS:
            raise Refused("bad_request", f"{len(errands)} errands: at most {MAX_ERRANDS}")
        cells = []
        for i, e in enumerate(errands):
            try:
                c = self.places.resolve(e)
            except PlaceError as err:
                raise Refused("bad_request", f"errand {i + 1}: {err}") from None
            why = self.usable(c)
            if why:
                raise Refused("bad_request", f"errand {i + 1}: cell {c} {why}")
            cells.append(c)
        prio = _number(req.get("priority", 0.0), "priority")
        if abs(prio) > MAX_PRIORITY:
            raise Refused("bad_request", f"priority {prio:g}: between -{MAX_PRIORITY:g} and {MAX_PRIORITY:g}")
        es = _number(req.get("earliest_start_s", 0.0), "earliest_start_s")
        dl = _number(req.get("deadline_s", 0.0), "deadline_s")
        if es < 0 or dl < 0:
            raise Refused("bad_request", "earliest_start_s and deadline_s must be >= 0 (fleet time: simulated s "
                                         "from now; 0: none)")
        if dl and dl <= es:
            raise Refused("bad_request", f"deadline_s {dl:g} is not after earliest_start_s {es:g}")
        if not tid:
            while True:
                self._auto += 1
                tid = f"T{self._auto}"
                if tid not in self._ids:
                    break
        k = self.step_s
        task = self.pool.add(cells, priority=prio, earliest_start=math.ceil((now + es) / k) if es else 0,
                             deadline=math.floor((now + dl) / k) if dl else None, release=int(now / k), at=now)
        # a cell's errand as its number (``0016`` is 16), a place's as its name
        errands = [e if e in self.places.by_name else str(c) for e, c in zip(errands, cells, strict=True)]
        rec = TaskRecord(tid, task, errands, _tag(req.get("source")), now,
                         earliest_start=now + es if es else 0.0, deadline=now + dl if dl else 0.0)
        self.records[tid] = self.by_pool[task.id] = rec
        self._ids.add(tid)
        return rec

    # -- transitions (the dispatcher calls these; the pool keeps the states) ------------------------
    def assign(self, rec: TaskRecord, robot: str, agent: int, now: float) -> None:
        """Give ``rec`` to ``robot`` (pool agent index ``agent``)."""
        before = (rec.task.agent, rec.state)
        self.pool.assign(rec.task.id, agent, robot, at=now)
        self.changed |= (rec.task.agent, rec.state) != before

    def unassign(self, rec: TaskRecord, now: float) -> None:
        """Put an unopened task back in the queue."""
        self.pool.unassign(rec.task.id, at=now)
        self.changed = True

    def reach(self, rec: TaskRecord, now: float) -> bool:
        """Its robot stands on the next errand: advance; True when the task is done."""
        done = self.pool.reach(rec.task.id, int(now / self.step_s), at=now)
        if done:
            self._closed(rec)
            self.durations.append(now - rec.created)
        self.changed = True
        return done

    def close(self, rec: TaskRecord, state: TaskState, reason: str, now: float) -> None:
        """End an open task as ``failed`` or ``cancelled`` with ``reason`` (opened or not)."""
        if state is TaskState.CANCELLED:
            self.pool.cancel(rec.task.id, reason, at=now, active=True)
        else:
            self.pool.fail(rec.task.id, reason, at=now)
        self._closed(rec)

    def _closed(self, rec: TaskRecord) -> None:
        self.counts[rec.state] += 1
        self.by_pool.pop(rec.task.id, None)
        self.closed.append(rec.id)
        while len(self.closed) > KEEP_CLOSED:
            self.records.pop(self.closed.popleft(), None)
        self.changed = True

    def expire(self, now: float) -> list[TaskRecord]:
        """Fail every open task whose deadline passed (counted in ``deadline_missed``)."""
        late = [r for r in self.by_pool.values() if r.deadline and now > r.deadline]
        for r in late:
            self.close(r, TaskState.FAILED, f"deadline passed ({r.deadline - r.created:.0f} s after creation, "
                       f"fleet time)", now)
            self.deadline_missed += 1
        return late

    def fail_on_cell(self, cell: int, why: str, now: float) -> list[TaskRecord]:
        """Fail every open task with an errand still to do on ``cell`` (it became blocked)."""
        hit = [r for r in self.by_pool.values() if cell in r.task.errands[r.task.next_errand:]]
        for r in hit:
            self.close(r, TaskState.FAILED, f"errand cell {cell} {why}", now)
        return hit

    # -- views -----------------------------------------------------------------------------------
    def open_records(self) -> list[TaskRecord]:
        """Open tasks, oldest first."""
        return list(self.by_pool.values())

    def stats(self) -> dict:
        """Counts and times of closed tasks: queued, done, failed, cancelled, deadline_missed,
        mean_s and p95_s (s from creation to done; 0 without done tasks)."""
        d = sorted(self.durations)
        p95 = d[min(len(d) - 1, math.ceil(0.95 * len(d)) - 1)] if d else 0.0
        return {"queued": sum(1 for r in self.by_pool.values() if r.state is TaskState.QUEUED),
                "done": self.counts[TaskState.DONE], "failed": self.counts[TaskState.FAILED],
                "cancelled": self.counts[TaskState.CANCELLED], "deadline_missed": self.deadline_missed,
                "mean_s": sum(d) / len(d) if d else 0.0, "p95_s": p95}

    def message(self, seq: int, stamp: float, robots: list[dict]) -> dict:
        """The ``fleet/TaskList`` (JSON form) at fleet time ``stamp``."""
        shown = self.open_records() + [self.records[i] for i in list(self.closed)[-SHOW_CLOSED:] if i in self.records]
        self.changed = False
        return {"header": {"stamp": {"secs": int(stamp), "nsecs": int((stamp % 1) * 1e9)}, "frame_id": "map"},
                "seq": seq, "tasks": [r.message() for r in shown], "answers": list(self.answers), "robots": robots,
                **self.stats()}


def _tag(value) -> str:
    """A request's ``request`` or ``source`` as kept and echoed: text, its first :data:`MAX_TAG` characters."""
    return str(value or "")[:MAX_TAG]


def _number(v, what: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError, OverflowError):
        raise Refused("bad_request", f"{what} {short_repr(v)} is not a number") from None
    if not math.isfinite(x):
        raise Refused("bad_request", f"{what} must be finite")
    return x
