"""How much of each step's time limit the planner spends, set by how punctually its steps return.

Under the League's rules a step that overruns its limit (1000 ms) is an all-wait step, counted as a
timeout. The planner works to two marks inside the limit (:func:`~.runner.run_lifelong`): the
``deadline``, after which it starts nothing new (no new distance map or guide path; the lookahead of
small teams ends there), and ``hard``, where EPIBT's LNS of large teams stops. The margin past
``hard`` covers what the clock does not: a slow page fault, another process taking the core, the
garbage collector. How much margin that needs depends on the machine, so it is measured, not set:

- The marks start where a shared machine needs them (``deadline`` at 0.5 of the limit, ``hard`` at
  0.7), as they were set by hand before.
- Every step's wall time is compared with its ``hard`` mark. Over a window of steps, the worst
  lateness (how far past ``hard`` a step came back, 0 when none did) is the machine's noise.
- After a whole window in which the margin left past ``hard`` would still be ``factor`` times that
  worst lateness with the marks moved up by ``grow``, the marks move up (``hard`` at most ``top``).
- A step that comes back later than ``1 / factor`` of the margin puts the marks back where they
  started, and the window starts again: additive increase, a fall to the start on a sign of trouble,
  as a network's sender backs off (Jacobson, "Congestion avoidance and control", SIGCOMM 1988).

A quiet machine thus gives the planner up to ``top`` of its second; a loaded one keeps the margin of
the start. The gap between ``deadline`` and ``hard`` is kept as it starts. A stall of the machine is
a time, not a share of the limit: the margin past ``hard`` never shrinks below ``least_s`` (100 ms), so
under a short limit (300 ms and less) the marks never move.
"""
from __future__ import annotations

from collections import deque

__all__ = ["StepBudget"]


class StepBudget:
    """The marks of the next step, as shares of the limit (module docstring).

    limit_s: the step's limit (s); deadline, hard: the marks at the start (shares of the limit,
    0 < deadline <= hard < 1); top: the highest ``hard``; least_s: the least margin past ``hard`` (s);
    grow: how far the marks move up after a quiet window; window: steps per decision; factor: the
    margin past ``hard`` is kept at least this many times the worst lateness of the window.
    ``history``: (step, hard) at every change; ``falls``: steps that put the marks back. Raises
    ValueError for marks out of order or outside (0, 1), a limit or window below what makes sense.
    """

    def __init__(self, limit_s: float, deadline: float = 0.5, hard: float = 0.7, top: float = 0.9,
                 least_s: float = 0.1, grow: float = 0.05, window: int = 100, factor: float = 3.0):
        if not 0 < deadline <= hard <= top < 1:
            raise ValueError(f"marks must satisfy 0 < deadline <= hard <= top < 1, got {deadline}, {hard}, {top}")
        if limit_s <= 0 or window < 1 or factor <= 0 or grow <= 0 or least_s < 0:
            raise ValueError(f"limit_s > 0, window >= 1, factor > 0, grow > 0 and least_s >= 0, got {limit_s}, "
                             f"{window}, {factor}, {grow}, {least_s}")
        top = min(top, 1.0 - least_s / limit_s)
        self.start, self.gap, self.top, self.grow = hard, hard - deadline, max(hard, top), grow
        self.window, self.factor = window, factor
        self.hard = hard
        self._late: deque[float] = deque(maxlen=window)
        self.falls = 0
        self.history: list[tuple[int, float]] = [(0, hard)]
        self._step = 0

    @property
    def deadline(self) -> float:
        """The ``deadline`` mark (share of the limit)."""
        return self.hard - self.gap

    def observe(self, used: float) -> None:
        """One step's wall time as a share of the limit (scheduler and planner; over 1: a timeout)."""
        self._step += 1
        late = max(0.0, used - self.hard)
        if late * self.factor > 1.0 - self.hard:           # it ate a third of the margin: back to the start
            if self.hard != self.start:
                self.hard = self.start
                self.history.append((self._step, self.hard))
            self.falls += 1
            self._late.clear()
            return
        self._late.append(late)
        if len(self._late) < self.window:
            return
        up = min(self.top, self.hard + self.grow)
        if up > self.hard and max(self._late) * self.factor <= 1.0 - up:
            self.hard = up
            self.history.append((self._step, self.hard))
        self._late.clear()
