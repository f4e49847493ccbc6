"""Which planner answers, chosen by the run: a race between methods, scored on the robots' progress.

A density threshold chose the step planner for a whole run (EPIBT with LNS from so many robots per
free cell, PIBT with rollouts below), set on the maps it was measured on. A map it was not set on,
or a run whose flow changes (a team that jams after a few hundred steps), may want the other one.
So the run measures: the methods take turns in short windows and the one whose robots come
closest to their goals answers until the next race.

- **The score** of a step is the robots' progress: the fall of each robot's distance to its goal
  over the step (the distance maps' units, lane costs included), summed over the robots with a
  goal (:func:`progress`). A robot that reaches its goal scores its last distance; one that
  yields or waits scores nothing or less. It counts every robot every step, where tasks finished
  count a few robots every few dozen steps, so a window of ten steps tells methods apart.
- **The race.** The arms take windows of ``window`` steps in turn, round after round (A B A B:
  a trend in the flow falls on both); the first ``settle`` steps of a window are not scored (the
  flow settles from the other method's last plan). After ``rounds`` rounds the arm with the most
  progress a step answers, the one answering before the race unless another leads it by
  ``margin``; after the first round an arm that leads every other by ``decisive`` wins at once,
  so a method far behind costs one window; and with ``early``, the arm answering before the race
  keeps it as soon as every other arm has ``early`` scored steps and it leads each of them by
  ``decisive``, so a method far behind costs ``settle + early`` steps, not a window (the early stop
  of action elimination: an arm whose mean is far under the leader's is dropped before its turns
  are spent).
- **Races repeat**, ``hold`` steps after the last one, and the hold doubles each time the same
  arm wins again (to ``max_hold``) and starts over when another wins: the choice follows a run
  that changes, and costs little in a run that does not (successive elimination of arms:
  Even-Dar, Mannor and Mansour, "Action elimination and stopping conditions for the multi-armed
  bandit and reinforcement learning problems", JMLR 2006; the choice of an algorithm per
  instance by measuring it: Rice, "The algorithm selection problem", 1976).

The class is sans-I/O: :meth:`MethodRace.arm` names the arm for the coming step, and
:meth:`MethodRace.observe` takes that step's score.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .kernels import UNREACHABLE

__all__ = ["MethodRace", "progress"]


def progress(table: np.ndarray, slot: np.ndarray, before: np.ndarray, after: np.ndarray) -> float:
    """The robots' progress over one step: the sum of ``table[slot, before] - table[slot, after]``
    over the robots with a distance map (``slot >= 0``) whose goal they can reach from where they
    were. table: (rows, cells) distance maps (:class:`~.distances.DistanceCache`'s, uint16);
    slot: (n,) each robot's row (-1: none); before, after: (n,) cells."""
    has = np.flatnonzero(slot >= 0)
    if not len(has):
        return 0.0
    d0 = table[slot[has], before[has]].astype(np.int64)
    d1 = table[slot[has], after[has]].astype(np.int64)
    ok = (d0 < UNREACHABLE) & (d1 < UNREACHABLE)
    return float((d0[ok] - d1[ok]).sum())


class MethodRace:
    """Choose among ``arms`` (names) by racing them (module docstring).

    first: the index of the arm answering before the first race (and after it on a tie);
    window: steps an arm answers in a turn; settle: of those, the first ones not scored;
    rounds: turns of each arm in a race; margin: the share by which another arm must lead the one
    answering to take over; decisive: the share by which an arm leading every other after the first
    round wins at once; hold, max_hold: steps from one race's end to the next, first and at most;
    start: the step the first race begins (before it, ``first`` answers); early: scored steps of each
    other arm after which the arm answering keeps its place at once if it leads them all by
    ``decisive`` (0: no early stop).
    ``history`` lists each race: ``{"step", "scores": {arm: progress a step}, "chosen"}``.
    Raises ValueError for fewer than two arms, or for a window with no scored step."""

    def __init__(self, arms: Sequence[str], first: int = 0, window: int = 10, settle: int = 3, rounds: int = 2,
                 margin: float = 0.03, decisive: float = 0.25, hold: int = 200, max_hold: int = 1600,
                 start: int = 0, early: int = 0):
        if len(arms) < 2:
            raise ValueError(f"a race needs two arms or more, not {list(arms)}")
        if not 0 <= settle < window:
            raise ValueError(f"settle ({settle}) must leave steps of the window ({window}) to score")
        self.arms = list(arms)
        self.current = int(first)
        self.window, self.settle, self.rounds = window, settle, rounds
        self.margin, self.decisive, self.early = margin, decisive, int(early)
        self.hold0, self.max_hold = hold, max_hold
        self.hold = hold
        self.history: list[dict] = []
        self.switches = 0
        self._k = 0                 # steps observed
        self._start = int(start)    # the step the current (or next) race begins
        self._sum = np.zeros(len(arms))
        self._n = np.zeros(len(arms), dtype=np.int64)

    @property
    def racing(self) -> bool:
        """Whether the coming step is part of a race."""
        return self._k >= self._start

    def _turn(self) -> tuple[int, int]:
        """The coming step's (arm index, step within its window), in a race."""
        w, pos = divmod(self._k - self._start, self.window)
        order = [self.current] + [i for i in range(len(self.arms)) if i != self.current]
        return order[w % len(order)], pos

    def arm(self) -> str:
        """The arm that answers the coming step."""
        return self.arms[self._turn()[0] if self.racing else self.current]

    def observe(self, score: float) -> None:
        """Take the score of the step just answered by :meth:`arm`'s arm."""
        if not self.racing:
            self._k += 1
            return
        i, pos = self._turn()
        if pos >= self.settle:
            self._sum[i] += score
            self._n[i] += 1
        self._k += 1
        mean = self._sum / np.maximum(self._n, 1)
        others = np.arange(len(self.arms)) != self.current
        if (self.early and i != self.current and pos >= self.settle and self._n[self.current] > 0
                and (self._n[others] >= self.early).all() and self._leads(self.current, mean)):
            self._decide(mean)                      # every other arm far behind after its early steps
            return
        turns = (self._k - self._start) // self.window
        if (self._k - self._start) % self.window or turns % len(self.arms):
            return                                  # within a window, or a round not yet over
        if turns // len(self.arms) >= self.rounds or self._leads(int(np.argmax(mean)), mean):
            self._decide(mean)

    def _leads(self, i: int, mean: np.ndarray) -> bool:
        """Whether arm ``i`` (mean progress > 0) leads every other arm by ``decisive``."""
        return bool(mean[i] > 0 and (mean[i] >= (1 + self.decisive) * np.maximum(np.delete(mean, i), 0)).all())

    def _decide(self, mean: np.ndarray) -> None:
        best = int(np.argmax(mean))
        cur = mean[self.current]
        take = best != self.current and mean[best] > cur + self.margin * abs(cur)
        chosen = best if take else self.current
        scores = {a: round(float(m), 2) for a, m in zip(self.arms, mean, strict=True)}
        self.history.append({"step": self._start, "scores": scores, "chosen": self.arms[chosen]})
        if chosen == self.current:
            self.hold = min(self.max_hold, self.hold * 2) if len(self.history) > 1 else self.hold
        else:
            self.switches += 1
            self.hold = self.hold0
        self.current = chosen
        self._start = self._k + self.hold
        self._sum[:] = 0
        self._n[:] = 0
