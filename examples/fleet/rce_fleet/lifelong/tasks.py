"""The task model of a lifelong fleet: a task is an ordered list of errands (cells) with a
priority and an optional earliest start and deadline, and the pool that holds its state.

States (docs/design.md, section 7.2; the League of Robot Runners' task rules, start-kit v2.1.2
``TaskManager.cpp``): ``queued`` (open, no robot), ``assigned`` (a robot is on its way to
the first errand; the task may still be given to another robot), ``active`` (its robot
reached the first errand: "opened", never reassigned), ``done``, ``failed`` (its deadline
passed, or :meth:`TaskPool.fail` with a reason: an errand cell was blocked, its robot cannot
reach it), ``cancelled`` (by the operator; LoRR allows it only before the task is opened, an
operator of a live fleet at any time before it is done).

The pool owns every state: each :class:`Task` keeps the time it entered each state
(``times``), its history of (time, state, agent, robot) and, when it failed or was
cancelled, the reason. Times are in the caller's unit (steps in the simulator, fleet
seconds in :mod:`rce_fleet.operations.tasks_api`): each transition takes ``at``, and without it the
newest time the pool was given. Closed tasks stay readable (:meth:`TaskPool.get`) until
``keep_closed`` newer ones have closed.
"""
from __future__ import annotations

import enum
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

__all__ = ["Task", "TaskError", "TaskPool", "TaskState"]


class TaskState(enum.Enum):
    """Where a task is in its life (see the module docstring)."""

    QUEUED = "queued"
    ASSIGNED = "assigned"
    ACTIVE = "active"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


OPEN_STATES = (TaskState.QUEUED, TaskState.ASSIGNED, TaskState.ACTIVE)


class TaskError(ValueError):
    """A transition the rules forbid (e.g. reassigning an opened task); names task and state."""


@dataclass(eq=False)
class Task:
    """One task: ``errands`` (cells, in order), ``priority`` (higher first), optional
    ``earliest_start`` and ``deadline`` (time steps). ``next_errand`` indexes the errand the
    task waits for; ``agent`` is its robot (-1: none) and ``robot`` that robot's name when the
    caller gave one; ``release``/``finish`` are the steps it was revealed and finished (-1: not
    yet). ``times``: state value -> when the task last entered it; ``history``: (time, state
    value, agent, robot) per transition; ``reason``: why it failed or was cancelled."""

    id: int
    errands: tuple[int, ...]
    priority: float = 0.0
    earliest_start: int = 0
    deadline: int | None = None
    release: int = 0
    state: TaskState = TaskState.QUEUED
    agent: int = -1
    next_errand: int = 0
    finish: int = -1
    length: int = -1                      # steps from the first errand through the last (cached by the scheduler)
    extra: dict = field(default_factory=dict)
    robot: str = ""
    reason: str = ""
    times: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    reached: list = field(default_factory=list)   # the time each errand was reached, in order

    @property
    def open(self) -> bool:
        """Whether it is queued, assigned or active."""
        return self.state in OPEN_STATES

    def _enter(self, state: TaskState, at: float) -> None:
        self.state = state
        self.times[state.value] = at
        self.history.append((at, state.value, self.agent, self.robot))

    @property
    def opened(self) -> bool:
        """Whether its robot reached the first errand (LoRR: then it is never reassigned)."""
        return self.next_errand > 0

    @property
    def goal(self) -> int:
        """The cell of the next errand."""
        return self.errands[self.next_errand]


class TaskPool:
    """The tasks of a fleet and their transitions (each raises TaskError when the rules
    forbid it). ``open`` maps id -> task for queued, assigned and active tasks; ``closed``
    counts done, failed and cancelled tasks; ``ended`` holds the newest ``keep_closed``
    closed tasks, oldest first; ``finished`` counts done tasks."""

    def __init__(self, keep_closed: int = 1000):
        self.open: dict[int, Task] = {}
        self.closed: dict[TaskState, int] = {TaskState.DONE: 0, TaskState.FAILED: 0, TaskState.CANCELLED: 0}
        self.ended: deque[Task] = deque(maxlen=max(0, int(keep_closed)))
        self._ended_ids: dict[int, Task] = {}
        self.now = 0.0
        self._next_id = 0

    def __len__(self) -> int:
        return len(self.open)

    def __iter__(self) -> Iterator[Task]:
        return iter(self.open.values())

    @property
    def finished(self) -> int:
        """How many tasks are done."""
        return self.closed[TaskState.DONE]

    def _at(self, at: float | None) -> float:
        if at is not None:
            self.now = float(at)
        return self.now

    def add(self, errands: Sequence[int], *, priority: float = 0.0, earliest_start: int = 0,
            deadline: int | None = None, release: int = 0, task_id: int | None = None,
            at: float | None = None) -> Task:
        """Queue a new task (``at``: now; default ``release``); returns it. Raises TaskError for
        no errand or a duplicate id."""
        if not errands:
            raise TaskError("a task needs at least one errand")
        tid = self._next_id if task_id is None else int(task_id)
        if tid in self.open:
            raise TaskError(f"task {tid} already exists")
        self._next_id = max(self._next_id, tid + 1)
        t = Task(tid, tuple(int(e) for e in errands), priority, earliest_start, deadline, release)
        t._enter(TaskState.QUEUED, self._at(release if at is None else at))
        self.open[tid] = t
        return t

    def get(self, tid: int) -> Task:
        """Task ``tid``, open or among the ``keep_closed`` newest closed. Raises TaskError."""
        t = self.open.get(tid) or self._ended_ids.get(tid)
        if t is None:
            raise TaskError(f"no task {tid}")
        return t

    def _get(self, tid: int) -> Task:
        t = self.open.get(tid)
        if t is None:
            raise TaskError(f"task {tid} is not open")
        return t

    def assign(self, tid: int, agent: int, robot: str = "", at: float | None = None) -> Task:
        """Give task ``tid`` to ``agent`` (named ``robot``; queued or assigned-but-unopened
        tasks only)."""
        t = self._get(tid)
        if t.opened and t.agent != agent:
            raise TaskError(f"task {tid} was opened by agent {t.agent}; it cannot go to agent {agent}")
        if t.agent != agent or t.state is TaskState.QUEUED:
            t.agent, t.robot = int(agent), robot
            t._enter(TaskState.ACTIVE if t.opened else TaskState.ASSIGNED, self._at(at))
        return t

    def unassign(self, tid: int, at: float | None = None) -> Task:
        """Take task ``tid`` back from its robot, to the queue (not once opened)."""
        t = self._get(tid)
        if t.opened:
            raise TaskError(f"task {tid} was opened by agent {t.agent}; it cannot be taken back")
        t.agent, t.robot = -1, ""
        t._enter(TaskState.QUEUED, self._at(at))
        return t

    def reach(self, tid: int, step: int, at: float | None = None) -> bool:
        """The task's robot stands on its next errand at ``step`` (``at``: the time; default
        ``step``): advance; True when the task is done (it leaves the pool)."""
        t = self._get(tid)
        if t.agent < 0:
            raise TaskError(f"task {tid} has no robot")
        at = self._at(step if at is None else at)
        t.next_errand += 1
        t.reached.append(at)
        if t.next_errand >= len(t.errands):
            t.finish = step
            self._close(t, TaskState.DONE, "", at)
            return True
        if t.next_errand == 1:
            t._enter(TaskState.ACTIVE, at)
        return False

    def cancel(self, tid: int, reason: str = "", at: float | None = None, *, active: bool = False) -> Task:
        """Cancel an open task with ``reason``: an unopened one (LoRR's rule), or also an active
        one with ``active`` (an operator's cancel)."""
        t = self._get(tid)
        if t.opened and not active:
            raise TaskError(f"task {tid} is active; it cannot be cancelled")
        self._close(t, TaskState.CANCELLED, reason, self._at(at))
        return t

    def fail(self, tid: int, reason: str, at: float | None = None) -> Task:
        """Fail an open task (queued, assigned or active) with ``reason``."""
        t = self._get(tid)
        self._close(t, TaskState.FAILED, reason, self._at(at))
        return t

    def expire(self, step: int, at: float | None = None) -> list[Task]:
        """Fail every open task whose deadline is before ``step``; returns them."""
        late = [t for t in self.open.values() if t.deadline is not None and t.deadline < step]
        at = self._at(step if at is None else at)
        for t in late:
            self._close(t, TaskState.FAILED, f"deadline passed (step {t.deadline})", at)
        return late

    def _close(self, t: Task, state: TaskState, reason: str, at: float) -> None:
        del self.open[t.id]
        t.reason = reason
        t._enter(state, at)
        self.closed[state] += 1
        if self.ended.maxlen:
            if len(self.ended) == self.ended.maxlen:
                self._ended_ids.pop(self.ended[0].id, None)
            self.ended.append(t)
            self._ended_ids[t.id] = t
