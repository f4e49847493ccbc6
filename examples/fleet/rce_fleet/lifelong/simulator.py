"""The rules of a lifelong run, apart from any planner or scheduler: the League of Robot
Runners 2024 start-kit's (MAPF-Competition/Start-Kit v2.1.2, ``ActionModel.cpp``,
``TaskManager.cpp``, ``CompetitionSystem.cpp``), one function or method per rule:

- actions: MAPF_T (``F`` forward, ``R`` clockwise, ``C`` counter-clockwise, ``W`` wait;
  robots face east at the start) or the 4-neighbour model (move E/S/W/N or wait);
- :func:`check_actions`: a move off the map or into an obstacle, a vertex conflict or a
  swap conflict makes the step invalid, and then every robot waits;
- a step whose planner overran its time limit is an all-wait step, counted in
  ``numEntryTimeouts`` (the planner here is called synchronously; its late answer is dropped);
- :meth:`Simulator.reveal`: ``int(numTasksReveal * teamSize)`` tasks are open at any time,
  revealed from the task file in order and cyclically (task i visits line ``i mod m``);
- :meth:`Simulator.apply_schedule`: a task opened (first errand reached) by a robot is
  never given to another, nor may that robot drop it; an invalid proposal is refused whole
  and counted in ``numScheduleErrors``. An adopted proposal takes effect after the step's move
  (``TaskManager::update_tasks``), so ``actualSchedule`` records it at the next timestep
  (``t+1:task``), and records every change of a robot's task since its last entry, ``-1``
  (none) included: a robot whose task went to another, or that finished one and got none;
- :meth:`Simulator.check_errands`: an errand is done when its robot stands on it.

:meth:`Simulator.output` writes the start-kit's output JSON; :func:`replay` re-runs one
under these rules.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .grid import HEADING_NAMES, LifelongGrid
from .kernels import ACT_C, ACT_F, ACT_R, ACT_W, MOVE_WAIT
from .tasks import TaskPool

__all__ = ["MAPF", "MAPF_T", "Simulator", "StepReport", "check_actions", "replay", "schedule_entries", "turned"]

MAPF_T = "MAPF_T"
MAPF = "MAPF"
T_LETTERS = "FRCW"          # index = ACT_F, ACT_R, ACT_C, ACT_W
M_LETTERS = "RDLUW"         # 4-neighbour: right (east), down (south), left (west), up (north), wait


def turned(head: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """(n,) headings after MAPF_T ``actions`` (n,): ``R`` adds a quarter turn clockwise, ``C``
    takes one away, modulo 4; the rest keep theirs."""
    new_head = head.copy()
    new_head[actions == ACT_R] = (head[actions == ACT_R] + 1) % 4
    new_head[actions == ACT_C] = (head[actions == ACT_C] + 3) % 4
    return new_head


def _apply(grid: LifelongGrid, pos: np.ndarray, head: np.ndarray, actions: np.ndarray, model: str):
    """Cells and headings after ``actions`` (no checks); -1 for a move off the map or into an obstacle."""
    if model == MAPF_T:
        fwd = actions == ACT_F
        new_pos = pos.copy()
        new_pos[fwd] = grid.nbr[pos[fwd], head[fwd]]
        return new_pos, turned(head, actions)
    mv = actions != MOVE_WAIT
    new_pos = pos.copy()
    new_pos[mv] = grid.nbr[pos[mv], actions[mv]]
    return new_pos, head.copy()


def check_actions(grid: LifelongGrid, pos: np.ndarray, head: np.ndarray, actions: np.ndarray,
                  model: str = MAPF_T) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, str]]]:
    """Apply one step's joint action under the rules.

    pos, head, actions: (n,) int arrays (cells, headings 0-3, action codes of
    :mod:`.kernels`). Returns (new_pos, new_head, errors); errors lists (agent1, agent2,
    description) for every unallowed move (agent2 = -1), vertex conflict and swap
    conflict. When there is any error the returned state is the unchanged one (all wait).
    Raises ValueError for an unknown action code or a wrong shape.
    """
    n = pos.shape[0]
    actions = np.asarray(actions, dtype=np.int64)
    if actions.shape != (n,):
        raise ValueError(f"expected {n} actions, got shape {actions.shape}")
    top = 3 if model == MAPF_T else MOVE_WAIT
    if n and (actions.min() < 0 or actions.max() > top):
        raise ValueError(f"action codes must be 0..{top} for {model}")
    new_pos, new_head = _apply(grid, pos, head, actions, model)
    errors: list[tuple[int, int, str]] = []
    for a in np.flatnonzero(new_pos < 0):
        errors.append((int(a), -1, "unallowed move"))
    ok = new_pos >= 0
    cells = np.where(ok, new_pos, pos)
    order = np.argsort(cells, kind="stable")
    sc = cells[order]
    dup = np.flatnonzero(sc[1:] == sc[:-1])
    for k in dup:
        errors.append((int(order[k]), int(order[k + 1]), "vertex conflict"))
    # swap: a moves into b's cell while b moves into a's
    owner = {int(c): i for i, c in enumerate(pos)}
    for a in np.flatnonzero(cells != pos):
        b = owner.get(int(cells[a]))
        if b is not None and b > a and cells[b] == pos[a]:
            errors.append((int(a), int(b), "edge conflict"))
    if errors:
        return pos.copy(), head.copy(), errors
    return cells, new_head, errors


@dataclass
class StepReport:
    """What one step did: its number, whether the planner's actions were refused (invalid)
    or late (timed out), errands and tasks finished in it."""

    step: int
    invalid: bool = False
    timed_out: bool = False
    schedule_refused: bool = False
    errands_done: int = 0
    tasks_done: int = 0
    errors: list = field(default_factory=list)


class Simulator:
    """A lifelong run under the rules (module docstring).

    grid: the map; starts: (n,) cells; task_source: the task file's errand tuples;
    reveal: how many tasks are open at any time; model: ``"MAPF_T"`` or ``"MAPF"``.
    State: ``t`` (steps done), ``pos``/``head`` ((n,) int64), ``pool`` (open tasks),
    ``assignment`` ((n,) task id per robot, -1 none). Raises ValueError for a start cell that
    is not free or two robots on one cell.
    """

    def __init__(self, grid: LifelongGrid, starts: Sequence[int], task_source: Sequence[Sequence[int]], reveal: int,
                 model: str = MAPF_T, record: bool = True):
        if model not in (MAPF_T, MAPF):
            raise ValueError(f"unknown action model {model!r}")
        self.grid, self.model, self.record = grid, model, record
        self.pos = np.asarray(starts, dtype=np.int64).copy()
        n = self.pos.shape[0]
        bad = [int(c) for c in self.pos if not grid.is_free(int(c))]
        if bad:
            raise ValueError(f"start cells {bad[:5]} are not free")
        if len(set(self.pos.tolist())) != n:
            raise ValueError("two robots start on one cell")
        self.n = n
        self.head = np.zeros(n, dtype=np.int64)          # everybody faces east
        self.start = self.pos.copy()
        self.task_source = [tuple(int(e) for e in t) for t in task_source]
        if not self.task_source:
            raise ValueError("no task")
        self.reveal_count = int(reveal)
        self.pool = TaskPool()
        self.assignment = np.full(n, -1, dtype=np.int64)
        self.t = 0
        self.revealed = 0
        self.finished = 0
        self.timeouts = 0
        self.invalid_steps = 0
        self.schedule_errors: list[tuple[int, int, int, int, str]] = []
        self.errors: list[tuple[int, int, int, str]] = []
        self.events: list[tuple[int, int, int, int]] = []
        self.task_log: list[tuple[int, int, tuple[int, ...]]] = []
        self.actual: list[np.ndarray] = []
        self.planned: list[np.ndarray] = []
        self.planner_times: list[float] = []
        self.actual_schedule: list[list[str]] = [[] for _ in range(n)]
        self._recorded = np.full(n, -1, dtype=np.int64)     # each robot's task as its last entry says
        self.cost = np.zeros(n, dtype=np.int64)
        self.finished_at: list[int] = []
        self.reveal()

    # -- rules ----------------------------------------------------------------------
    def reveal(self) -> int:
        """Reveal tasks in file order, cyclically, until ``reveal`` are open; returns how many."""
        k = 0
        while len(self.pool) < self.reveal_count:
            tid = self.revealed
            errands = self.task_source[tid % len(self.task_source)]
            self.pool.add(errands, release=self.t, task_id=tid)
            if self.record:
                self.task_log.append((tid, self.t, errands))
            self.revealed += 1
            k += 1
        return k

    def validate_schedule(self, proposal: np.ndarray) -> list[tuple[int, int, int, int, str]]:
        """The schedule errors of ``proposal`` ((n,) task id per robot, -1 none), as the
        start-kit's (task, agent1, agent2, step, description): an unknown or finished task,
        one task for two robots, an opened task given to another robot, a robot taken off
        the task it opened."""
        errs = []
        seen: dict[int, int] = {}
        for a, tid in enumerate(proposal.tolist()):
            cur = int(self.assignment[a])
            if cur >= 0 and cur != tid and self.pool.open[cur].opened:
                errs.append((cur, a, -1, self.t, "robot dropped the task it opened"))
            if tid < 0:
                continue
            t = self.pool.open.get(tid)
            if t is None:
                errs.append((tid, a, -1, self.t, "task is not open"))
                continue
            if tid in seen:
                errs.append((tid, seen[tid], a, self.t, "task assigned to two robots"))
            seen[tid] = a
            if t.opened and t.agent != a:
                errs.append((tid, t.agent, a, self.t, "task opened by another robot"))
        return errs

    def apply_schedule(self, proposal: np.ndarray | None) -> bool:
        """Adopt a valid ``proposal`` (False and the errors recorded when it is refused;
        None proposes the current schedule again)."""
        if proposal is None:
            self._record_schedule()
            return True
        proposal = np.asarray(proposal, dtype=np.int64)
        if proposal.shape != (self.n,):
            raise ValueError(f"expected {self.n} task ids, got shape {proposal.shape}")
        errs = self.validate_schedule(proposal)
        if errs:
            self.schedule_errors.extend(errs)
            return False
        changed = np.flatnonzero(proposal != self.assignment)
        for a in changed:
            old = int(self.assignment[a])
            if old >= 0 and self.pool.open[old].agent == a:
                self.pool.unassign(old)
        for a in changed:
            tid = int(proposal[a])
            if tid >= 0:
                self.pool.assign(tid, int(a))
        self.assignment = proposal.copy()
        self._record_schedule()
        return True

    def _record_schedule(self) -> None:
        """``actualSchedule`` entries at the next timestep for every robot whose task differs from
        its last entry, as the start-kit's ``TaskManager::set_task_assignment`` writes them."""
        if not self.record:
            return
        for a in np.flatnonzero(self.assignment != self._recorded).tolist():
            self.actual_schedule[a].append(f"{self.t + 1}:{int(self.assignment[a])}")
        self._recorded[:] = self.assignment

    def check_errands(self) -> tuple[int, int]:
        """Advance every task whose robot stands on its next errand; returns (errands, tasks) done."""
        errands = tasks = 0
        for a in np.flatnonzero(self.assignment >= 0):
            t = self.pool.open[int(self.assignment[a])]
            if t.goal == self.pos[a]:
                seq = t.next_errand
                done = self.pool.reach(t.id, self.t)
                errands += 1
                if self.record:
                    self.events.append((self.t, int(a), t.id, seq + 1))     # errands reached, as the start-kit's
                if done:
                    tasks += 1
                    self.assignment[a] = -1
                    self.finished_at.append(self.t)
        self.finished += tasks
        return errands, tasks

    def step(self, actions: np.ndarray | None, schedule: np.ndarray | None = None,
             plan_time_s: float = 0.0, timed_out: bool = False) -> StepReport:
        """Run one time step: adopt ``schedule`` (if valid), execute ``actions`` (all wait
        when invalid, missing or ``timed_out``), then errands and reveals. Returns its report."""
        rep = StepReport(self.t)
        if timed_out or actions is None:
            rep.timed_out = True
            self.timeouts += 1
            schedule = None
        if not self.apply_schedule(schedule):
            rep.schedule_refused = True
        wait = np.full(self.n, ACT_W if self.model == MAPF_T else MOVE_WAIT, dtype=np.int64)
        acts = wait if rep.timed_out else np.asarray(actions, dtype=np.int64)
        new_pos, new_head, errs = check_actions(self.grid, self.pos, self.head, acts, self.model)
        if errs:
            rep.invalid, rep.errors = True, errs
            self.invalid_steps += 1
            self.errors.extend((a, b, self.t, msg) for a, b, msg in errs)
            acts = wait
        self.cost += self.assignment >= 0
        self.pos, self.head = new_pos, new_head
        if self.record:
            self.actual.append(acts.astype(np.uint8))
            self.planned.append((wait if actions is None else np.asarray(actions)).astype(np.uint8))
            self.planner_times.append(float(plan_time_s))
        self.t += 1
        rep.errands_done, rep.tasks_done = self.check_errands()
        self.reveal()
        return rep

    # -- output ---------------------------------------------------------------------------
    def output(self, version: str = "2024 LoRR") -> dict:
        """The start-kit's output JSON (``Input_Output_Format.md``) as a dict."""
        letters = T_LETTERS if self.model == MAPF_T else M_LETTERS
        lut = np.frombuffer(letters.encode(), dtype=np.uint8)

        def paths(rows: list[np.ndarray]) -> list[str]:
            if not rows:
                return [""] * self.n
            m = lut[np.stack(rows, axis=1)]          # (n, steps) letters
            return [",".join(r.tobytes().decode()) for r in m]

        cols = self.grid.cols
        return {
            "actionModel": self.model,
            "version": version,
            "teamSize": self.n,
            "start": [[int(c) // cols, int(c) % cols, HEADING_NAMES[0]] for c in self.start],
            "numTaskFinished": self.finished,
            "sumOfCost": int(self.cost.sum()),
            "makespan": self.t,
            "actualPaths": paths(self.actual),
            "plannerPaths": paths(self.planned),
            "plannerTimes": self.planner_times,
            "errors": [list(e) for e in self.errors],
            "events": [list(e) for e in self.events],
            "tasks": [[tid, rel, [v for e in errands for v in divmod(e, cols)]] for tid, rel, errands in self.task_log],
            "actualSchedule": [",".join(s) for s in self.actual_schedule],
            "plannerSchedule": [",".join(s) for s in self.actual_schedule],
            "numPlannerErrors": len(self.errors),
            "numScheduleErrors": len(self.schedule_errors),
            "numEntryTimeouts": self.timeouts,
            "scheduleErrors": [list(e) for e in self.schedule_errors],
        }


def replay(grid: LifelongGrid, task_source: Sequence[Sequence[int]], reveal: int, output: dict) -> Simulator:
    """Re-run an output JSON under the rules: its starts, its ``actualPaths`` and its
    ``actualSchedule``. Returns the simulator; compare its ``finished`` with the output's
    ``numTaskFinished``. Raises ValueError for a malformed output."""
    model = output.get("actionModel", MAPF_T)
    letters = T_LETTERS if model == MAPF_T else M_LETTERS
    starts = [r * grid.cols + c for r, c, *_ in output["start"]]
    sim = Simulator(grid, starts, task_source, reveal, model, record=False)
    steps = int(output["makespan"])
    acts = np.full((sim.n, steps), ACT_W if model == MAPF_T else MOVE_WAIT, dtype=np.int64)
    for a, s in enumerate(output["actualPaths"]):
        codes = [letters.index(x) for x in s.split(",")] if s else []
        if len(codes) != steps:
            raise ValueError(f"agent {a}: {len(codes)} actions for makespan {steps}")
        acts[a] = codes
    sched = schedule_entries(output["actualSchedule"])
    for t in range(steps):
        prop = None
        if t + 1 in sched:                     # entries at t+1 take effect after the move of step t
            prop = sim.assignment.copy()
            for a, tid in sched[t + 1]:
                prop[a] = tid
        sim.step(acts[:, t], prop)
    return sim


def schedule_entries(actual_schedule: Sequence[str]) -> dict[int, list[tuple[int, int]]]:
    """``actualSchedule`` (one ``"T:task,T:task,..."`` string per robot) -> {T: [(robot, task)]}.
    Raises ValueError naming the robot and the entry that is not ``T:task``."""
    sched: dict[int, list[tuple[int, int]]] = {}
    for a, s in enumerate(actual_schedule):
        for item in filter(None, s.split(",")):
            try:
                t, tid = (int(x) for x in item.split(":"))
            except ValueError:
                raise ValueError(f"actualSchedule of robot {a}: expected 'timestep:task', got {item!r}") from None
            sched.setdefault(t, []).append((a, tid))
    return sched

