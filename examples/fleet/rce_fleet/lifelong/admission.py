"""How many robots may hold a task, set at run time by the flow they make.

A team larger than its map's corridors can carry jams: robots routed through a packed corridor
mouth wait there, more arrive, and the jam grows until most of the team waits (docs/lifelong.md,
"A jam on GAME"). A jam, once grown, stays: its robots hold tasks they have opened, which cannot
be taken back. Fewer robots on the move finish more, but how many a map carries depends on its
corridors and on where the tasks are, so the bound is found while the team runs, as a network
finds its sending rate: additive increase, multiplicative decrease (Chiu and Jain, "Analysis of
the increase and decrease algorithms for congestion avoidance in computer networks", 1989; TCP's
congestion avoidance, Jacobson, SIGCOMM 1988), from a bound that starts low.

The signal is the flow: the share of the robots holding a task that changed cell in a step, over
a window of steps. Below ``target`` the team is jamming and the bound falls to ``decrease`` of
the robots holding a task; above ``target + band`` it rises by ``increase`` of the team (while
the bound is what holds robots back). The scheduler then takes unopened tasks back from the
robots farthest from them until the bound holds (:class:`~.scheduler.Scheduler`'s
``max_active``). A map whose robots turn often moves a smaller share of them when nothing jams
(0.69 on random-32-32-20 at 100 robots, 0.75 - 0.9 on the city, game and warehouse maps), so the
share moving alone holds back teams that flow. With the jam gate (``jam_factor``) the bound falls
only while robots also pack in (every free neighbour cell held by a robot: :func:`packed`) and
rises whenever they do not: a team that turns but flows keeps growing, a team pressing into a
passage is held back before its crowd packs solid (measured in docs/lifelong.md).

On a large map a fall acts late: opened tasks are never taken back, so the robots on a task fall
to the bound only as their tasks end, hundreds of steps on GAME, while a jam at the corridor mouths
grows over as many. A bound that falls by ``decrease`` and grows back then overshoots again and
again. So, with the gate, the bound also falls while robots pack in and the share moving is
``drop`` under its best since the last fall (a jam growing slowly is met before the share reaches
``target``), the first fall of a jam goes at once to ``ceiling`` of the bound it fell from, and the
bound never grows past that again, as TCP's slow-start threshold remembers the window that lost.
"""
from __future__ import annotations

from itertools import pairwise

import numpy as np

__all__ = ["FlowAdmission", "JamCut", "JamDetector", "jam_note", "jam_share", "packed"]


class FlowAdmission:
    """AIMD control of the number of robots holding a task (module docstring).

    team: robots in the team; window: steps per decision; target, band: the share of task
    holders that moved (per step, over the window) below which the bound falls, and the margin
    above it from which it rises; decrease: the factor it falls by; increase: the share of the
    team it rises by; floor: the lowest bound, as a share of the team; start: the first bound
    (robots; None: none); slow_start: the factor it grows by instead while it has not fallen yet
    (1: none); jam_factor, jam_least: with them the bound falls only while a jam grows (the share
    of holders packed in, :func:`packed`, over ``jam_factor`` times the first window's and over
    ``jam_least``) and rises whenever none does, whatever the share moving (None: the share moving
    alone decides); calm: with the gate, slow start grows the bound only while the packed share is
    under this share of a jam's (:func:`jam_share`), and by ``increase`` alone nearer one (None: until
    the first jam, whatever the packed share); drop: with the gate, the bound also falls while a jam
    grows and the share moving is this far below the best window's since the bound last fell (a jam
    that grows slowly is met before the share reaches ``target``; None: ``target`` alone); ceiling:
    the first fall of a jam goes at once to this share of the bound it fell from, and the bound
    never grows past it again (a jam at it lowers it the same way), as TCP's slow-start threshold
    remembers the window that lost (None: no ceiling). ``bound`` is None
    while no bound holds; ``decisions``: (step, share moving, bound, packed share) per window.
    Raises ValueError for a share outside (0, 1] or a window below 1.
    """

    def __init__(self, team: int, window: int = 25, target: float = 0.8, band: float = 0.05,
                 decrease: float = 0.85, increase: float = 0.02, floor: float = 0.1, start: int | None = None,
                 slow_start: float = 1.0, jam_factor: float | None = None, jam_least: float = 0.05,
                 calm: float | None = None, drop: float | None = None, ceiling: float | None = None):
        for name, v in (("target", target), ("decrease", decrease), ("increase", increase), ("floor", floor),
                        ("ceiling", 1.0 if ceiling is None else ceiling)):
            if not 0.0 < v <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {v}")
        if window < 1:
            raise ValueError(f"window must be at least 1 step, got {window}")
        self.team, self.window, self.target, self.band = team, window, target, band
        self.decrease, self.increase, self.floor = decrease, increase, max(1, int(floor * team))
        self.bound: int | None = None if start is None or start >= team else max(self.floor, int(start))
        self.slow_start = slow_start
        self.jam_factor, self.jam_least, self.calm, self.drop, self.ceiling = jam_factor, jam_least, calm, drop, ceiling
        self._first_packed: float | None = None
        self._best = 0.0                                  # the best share moving since the last fall
        self._cap: int | None = None                      # the ceiling's bound (robots), after a fall
        self._falling = False                             # the bound fell and has not risen since
        self._moved = self._holding = self._steps = self._packed = 0
        self.decisions: list[tuple[int, float, int | None, float]] = []

    def observe(self, step: int, moved: int, holding: int, packed_holders: int = 0) -> int | None:
        """Count one step: ``moved`` robots holding a task changed cell, ``packed_holders`` of them
        are packed in, of ``holding``. Returns the bound (robots), None for none."""
        self._moved += moved
        self._holding += holding
        self._packed += packed_holders
        self._steps += 1
        if self._steps < self.window:
            return self.bound
        share = self._moved / self._holding if self._holding else 1.0
        packed_share = self._packed / self._holding if self._holding else 0.0
        self._moved = self._holding = self._steps = self._packed = 0
        grow = self.slow_start
        if self.jam_factor is None:                       # the share moving alone decides
            fall, rise = share < self.target, share > self.target + self.band
        else:                                             # the jam gate
            if self._first_packed is None:
                self._first_packed = packed_share
            over = jam_share(self._first_packed, self.jam_factor, self.jam_least)
            jam = packed_share > over
            low = share < self.target or (self.drop is not None and share < self._best - self.drop)
            fall, rise = jam and low, not jam
            if self.calm is not None and packed_share >= self.calm * over:
                grow = 1.0                                # near a jam: additive only
        self._best = max(self._best, share)
        if fall:
            base = holding if self.bound is None else min(self.bound, holding)
            if self.ceiling is not None and not self._falling:     # the first fall of a jam
                self._cap = max(self.floor, int(self.ceiling * base))
            self.bound = max(self.floor, int(self.decrease * base))
            if self._cap is not None:                     # the first fall goes to the ceiling at once
                self.bound = min(self.bound, self._cap)
            self.slow_start, self._best, self._falling = 1.0, 0.0, True
        elif rise and self.bound is not None and holding >= self.bound - 1:
            grown = max(self.bound + max(1, int(self.increase * self.team)), int(self.bound * grow))
            self.bound = grown if self._cap is None else min(grown, max(self._cap, self.bound))
            self._falling = False
            if self.bound >= self.team:
                self.bound = None
        self.decisions.append((step, round(share, 3), self.bound, round(packed_share, 3)))
        return self.bound


def _cuts_said(changes: list) -> str:
    """:class:`JamCut`'s ``changes`` [(step, bound)] in words ("" for none)."""
    if not changes:
        return ""
    (step, bound), last = changes[0], changes[-1]
    cuts = sum(1 for (_, b), (_, a) in pairwise(changes) if b is None or (a is not None and a < b))
    said = f"; at most {bound} robots held a task from step {step}, cut from those holding one"
    if len(changes) > 1:
        said += f"; the bound grew back as the jam cleared, from step {changes[1][0]}"
    if cuts:
        said += f", and was cut again {({1: 'once', 2: 'twice'}).get(cuts, f'{cuts} times')} at another jam"
    if len(changes) > 1:
        said += (f"; no bound held from step {last[0]}" if last[1] is None
                 else f"; at most {last[1]} robots held a task at the end")
    return said


def jam_share(first: float, factor: float, least: float) -> float:
    """The packed share (:func:`packed`, over a window) over which a jam grows: ``factor`` times the
    first window's ``first``, and at least ``least``."""
    return max(least, factor * first)


def packed(nbr: np.ndarray, pos: np.ndarray, occupied: np.ndarray) -> np.ndarray:
    """Which robots are packed in: every free neighbour cell of theirs held by a robot.

    nbr: (cells, 4) int32 neighbours (-1: blocked, :class:`~.grid.LifelongGrid`); pos: (n,)
    int64 cells; occupied: (cells + 1,) bool, True where a robot stands, its last entry False
    (the one a blocked neighbour's -1 reads). Returns (n,) bool."""
    nb = nbr[pos]
    return (occupied[nb] | (nb < 0)).all(axis=1)


class JamDetector:
    """Tells a jam growing from a team that is merely dense, by how many robots are packed in.

    A jam on a map of open areas joined by narrow passages starts as robots pressing into a passage
    from both sides; the crowd packs solid, and every robot routed through it joins (docs/lifelong.md,
    "Maps it was not tuned on"). The share of the robots holding a task whose every free neighbour
    cell is held by a robot (:func:`packed`) then grows window after window: on ost003d with 2,000
    robots 0.007 in the first 25 steps, 0.06 by step 50, 0.36 by step 100. A team that is dense but
    flows packs a share that stays flat (random-32-32-20 at 200 robots: 0.045 - 0.098 all run). So
    a jam is a share over ``factor`` times the first window's and over ``least``, in ``persist``
    windows in a row: a team setting out packs in for a while and then spreads (WAREHOUSE's 10,000
    robots under strong lanes: 0.053, 0.115, 0.150, 0.163, then 0.137 and falling), and a jam stays.
    It is seen too late to prevent (by then most robots have opened their tasks, which are never taken
    back): it is a diagnosis, reported so that a user can turn the run-time bound on (``--admission on``).

    window: steps per window; factor, least, persist: as above. ``jam_at``: the step that closed
    the first window showing a jam (None: none yet); ``jammed``: whether the last ``persist``
    windows were all over the mark (a jam now); ``shares``: the share of each window. Raises
    ValueError for a window or persist below 1.
    """

    def __init__(self, window: int = 25, factor: float = 3.0, least: float = 0.15, persist: int = 2):
        if window < 1:
            raise ValueError(f"window must be at least 1 step, got {window}")
        if persist < 1:
            raise ValueError(f"persist must be at least 1 window, got {persist}")
        self.window, self.factor, self.least, self.persist = window, factor, least, persist
        self._over = 0
        self.jammed = False
        self.jam_at: int | None = None
        self.shares: list[float] = []
        self._packed = self._holding = self._steps = 0

    def observe(self, step: int, packed_holders: int, holding: int) -> bool:
        """Count one step: ``packed_holders`` of the ``holding`` robots with a task are packed in.
        Returns True once a jam has been seen."""
        self._packed += packed_holders
        self._holding += holding
        self._steps += 1
        if self._steps == self.window:
            share = self._packed / self._holding if self._holding else 0.0
            self._packed = self._holding = self._steps = 0
            self.shares.append(round(share, 3))
            self._over = self._over + 1 if share > self.mark else 0
            self.jammed = self._over >= self.persist
            if self.jam_at is None and self.jammed:
                self.jam_at = step
        return self.jam_at is not None

    @property
    def mark(self) -> float:
        """The packed share over which a window shows a jam (:func:`jam_share` of the first
        window's; ``least`` before the first window closes)."""
        return jam_share(self.shares[0], self.factor, self.least) if self.shares else self.least


class JamCut:
    """The bound on robots holding a task on a map of aisles, where no other bound holds: cut when a
    jam is seen, lifted as it clears.

    Robots in one-cell aisles that jam head-on stay jammed while more are routed in; the robots on
    a task can only fall as their tasks end, so once ``detector`` (:class:`JamDetector`) sees a jam,
    the bound falls at once to ``cut`` of the robots then holding a task (WAREHOUSE, 10,000 robots:
    a jam at step 474 cut to 7,000, and the packed share back from 0.325 to 0.19 by step 825). A
    bound kept there after the jam cleared holds the team under what the map carries (the same run:
    1,866 - 2,270 tasks per 100 steps at 7,000, against 2,560 - 3,300 at 10,000 in a run that did
    not jam). So once the packed share has been under ``clear`` of the detector's mark for
    ``detector.persist`` windows in a row, the bound grows back by ``increase`` of the team per window
    while the share stays there and the robots holding a task fill it (additive increase, as
    :class:`FlowAdmission`'s), to no bound; a share between that and the mark holds it, and a jam
    seen again cuts it again, from the robots holding a task then.

    detector: the run's :class:`JamDetector` (this observes it); team: robots in the team; cut,
    clear, increase: shares in (0, 1] as above. ``bound``: robots (None: no bound); ``changes``:
    (step, bound) each time the bound changed. Raises ValueError for a share outside (0, 1].
    """

    def __init__(self, detector: JamDetector, team: int, cut: float = 0.7, clear: float = 0.8,
                 increase: float = 0.02):
        for name, v in (("cut", cut), ("clear", clear), ("increase", increase)):
            if not 0.0 < v <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {v}")
        self.detector, self.team, self.cut, self.clear = detector, team, cut, clear
        self.increase = max(1, int(increase * team))
        self.bound: int | None = None
        self.changes: list[tuple[int, int | None]] = []
        self._cutting = False                             # cut, and the jam not yet cleared
        self._calm = 0                                    # windows in a row under the clear mark

    def observe(self, step: int, packed_holders: int, holding: int) -> int | None:
        """Count one step as :meth:`JamDetector.observe` does. Returns the bound (robots), None
        for none."""
        d = self.detector
        windows = len(d.shares)
        d.observe(step, packed_holders, holding)
        if len(d.shares) == windows:                      # the window goes on
            return self.bound
        calm = d.shares[-1] < self.clear * d.mark
        self._calm = self._calm + 1 if calm else 0
        bound = self.bound
        if d.jammed and not self._cutting:
            bound, self._cutting = max(1, int(self.cut * holding)), True
        elif self._cutting and self._calm >= d.persist:
            self._cutting = False                         # cleared: the bound may grow from the next window
        elif not self._cutting and bound is not None and calm and holding >= bound - 1:
            bound += self.increase
            if bound >= self.team:
                bound = None
        if bound != self.bound:
            self.bound = bound
            self.changes.append((step, bound))
        return self.bound


def jam_note(stats: dict) -> str | None:
    """What to tell the user of a run whose :class:`JamDetector` saw a jam (``stats`` of
    :func:`~.runner.run_lifelong`: ``jam_at``, ``packed_shares``, ``aisle_map``, ``jam_bounds``); None
    when it saw none. On a map of aisles (``aisle_map``: at least :data:`~.runner.AISLE_SHARE` of its
    free cells in one-cell lanes) it says what the run's :class:`JamCut` did, and does not advise the
    run-time bound: there it finished fewer (SORTATION, 10,000 robots, 1,000 steps: 14,367 against
    18,631)."""
    if stats.get("jam_at") is None:
        return None
    shares = stats["packed_shares"]
    jam = (f"the team jammed from step {stats['jam_at']}: the share of robots with a task packed in (every free "
           f"neighbour cell held by a robot) rose from {shares[0]:.3f} to {max(shares):.3f}")
    if stats.get("aisle_map"):
        return jam + _cuts_said(stats.get("jam_bounds") or []) + ("; on this map of aisles the run-time bound "
                                                                  "(--admission on) finished fewer, not more")
    return (jam + "; on a game map (open areas joined by a few passages) --admission on keeps fewer robots moving "
            "and finishes more (docs/lifelong.md, \"Maps it was not tuned on\")")
