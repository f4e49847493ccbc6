"""The task model of a lifelong fleet: a task is an ordered list of errands (cells) with a
priority and an optional earliest start and deadline, and the pool that holds its state.

States (DESIGN section 9; the League of Robot Runners' task rules, start-kit v2.1.2
``TaskManager.cpp``): ``queued`` (open, no robot), ``assigned`` (a robot is on its way to
the first errand; the task may still be given to another robot), ``active`` (its robot
reached the first errand: "opened", never reassigned), ``done``, ``failed`` (its deadline
passed), ``cancelled`` (by the operator, before it was opened).
"""
from __future__ import annotations

import enum
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
    task waits for; ``agent`` is its robot (-1: none); ``release``/``finish`` are the steps
    it was revealed and finished (-1: not yet)."""

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

    @property
    def opened(self) -> bool:
        """Whether its robot reached the first errand (LoRR: then it is never reassigned)."""
        return self.next_errand > 0

    @property
    def goal(self) -> int:
        """The cell of the next errand."""
        return self.errands[self.next_errand]


class TaskPool:
    """The open tasks of a fleet and their transitions (each raises TaskError when the
    rules forbid it). ``open`` maps id -> task for queued, assigned and active tasks;
    ``finished`` counts done tasks."""

    def __init__(self):
        self.open: dict[int, Task] = {}
        self.closed: dict[TaskState, int] = {TaskState.DONE: 0, TaskState.FAILED: 0, TaskState.CANCELLED: 0}
        self._next_id = 0

    def __len__(self) -> int:
        return len(self.open)

    def __iter__(self) -> Iterator[Task]:
        return iter(self.open.values())

    @property
    def finished(self) -> int:
        """How many tasks are done."""
        return self.closed[TaskState.DONE]

    def add(self, errands: Sequence[int], *, priority: float = 0.0, earliest_start: int = 0,
            deadline: int | None = None, release: int = 0, task_id: int | None = None) -> Task:
        """Queue a new task; returns it. Raises TaskError for no errand or a duplicate id."""
        if not errands:
            raise TaskError("a task needs at least one errand")
        tid = self._next_id if task_id is None else int(task_id)
        if tid in self.open:
            raise TaskError(f"task {tid} already exists")
        self._next_id = max(self._next_id, tid + 1)
        t = Task(tid, tuple(int(e) for e in errands), priority, earliest_start, deadline, release)
        self.open[tid] = t
        return t

    def _get(self, tid: int) -> Task:
        t = self.open.get(tid)
        if t is None:
            raise TaskError(f"task {tid} is not open")
        return t

    def assign(self, tid: int, agent: int) -> Task:
        """Give task ``tid`` to ``agent`` (queued or assigned-but-unopened tasks only)."""
        t = self._get(tid)
        if t.opened and t.agent != agent:
            raise TaskError(f"task {tid} was opened by agent {t.agent}; it cannot go to agent {agent}")
        t.agent = int(agent)
        if t.state is TaskState.QUEUED:
            t.state = TaskState.ASSIGNED
        return t

    def unassign(self, tid: int) -> Task:
        """Take task ``tid`` back from its robot (not once opened)."""
        t = self._get(tid)
        if t.opened:
            raise TaskError(f"task {tid} was opened by agent {t.agent}; it cannot be taken back")
        t.agent = -1
        t.state = TaskState.QUEUED
        return t

    def reach(self, tid: int, step: int) -> bool:
        """The task's robot stands on its next errand at ``step``: advance; True when the task
        is done (it leaves the pool)."""
        t = self._get(tid)
        if t.agent < 0:
            raise TaskError(f"task {tid} has no robot")
        t.next_errand += 1
        t.state = TaskState.ACTIVE
        if t.next_errand >= len(t.errands):
            t.state, t.finish = TaskState.DONE, step
            self._close(t)
            return True
        return False

    def cancel(self, tid: int) -> Task:
        """Cancel an unopened task."""
        t = self._get(tid)
        if t.opened:
            raise TaskError(f"task {tid} is active; it cannot be cancelled")
        t.state, t.agent = TaskState.CANCELLED, -1
        self._close(t)
        return t

    def expire(self, step: int) -> list[Task]:
        """Fail every open task whose deadline is before ``step``; returns them."""
        late = [t for t in self.open.values() if t.deadline is not None and t.deadline < step]
        for t in late:
            t.state = TaskState.FAILED
            self._close(t)
        return late

    def _close(self, t: Task) -> None:
        del self.open[t.id]
        self.closed[t.state] += 1
