"""A whole lifelong run: the simulator (rules), the scheduler and the planner, step by
step, each step's scheduler + planner call timed by the wall clock against the limit.

The step's work has a deadline (the scheduler's share ends at half of it): past it no new
distance map is computed (the scheduler estimates by Manhattan distance, a robot whose goal
map is missing waits), and a later mark, ``hard``, where EPIBT's LNS stops, so the call
returns with margin. The marks start at 0.5 and 0.7 of the limit and move up while the steps
come back on time (:class:`~.budget.StepBudget`: the margin is measured, not set), or stay at
``budget_frac`` and 0.7 when that is given. A call that still overruns the limit is an
all-wait step, counted as a timeout.
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .admission import FlowAdmission, JamCut, JamDetector, packed
from .pursuit import check_pursue, pursuing, steps_left
from .budget import StepBudget
from .distances import DistanceCache, cache_bytes_for
from .flow import TrafficFlow
from .flow import warm_up as flow_warm_up
from .guidance import keep_right_costs, lane_costs
from .kernels import warm_up
from .epibt import warm_up as epibt_warm_up
from .window import warm_up as window_warm_up
from .lorr import LorrProblem
from .pibt import PIBTPlanner
from .race import MethodRace, progress as race_progress
from .refine import warm_up as refine_warm_up
from .replan import ReplanPlanner
from .scheduler import make_scheduler
from .simulator import MAPF_T, Simulator

__all__ = ["ACTIVE_DENSITY", "ACTIVE_FRAC", "ADMISSION_CELLS", "ADMISSION_DENSITY", "ADMISSION_JAM",
           "ADMISSION_JAM_DENSITY", "ADMISSION_SMALL", "ADMISSION_SMALL_START", "ADMISSION_START",
           "AISLE_ACTIVE_FRAC", "AISLE_EPIBT_DENSITY", "AISLE_JAM_CUT", "AISLE_LANES_JAM_LEAST", "AISLE_SHARE",
           "CRISSCROSS_DENSITY", "CROWD_TEAM", "CROWD_W", "EPIBT_ACTIVE_FRAC", "EPIBT_BIAS", "EPIBT_DENSITY",
           "EPIBT_LNS_FRAC", "GUIDE_DENSITY", "KEEP_RIGHT", "LANES", "OPEN_LANES", "PACKED_DENSITY", "PURSUE_FRAC",
           "RACE", "REPLAN_CORRIDORS", "REPLAN_DENSITY", "RunResult", "SMALL_MAP_CELLS", "SMALL_MAP_STUCK",
           "WINDOW_DENSITY", "WINDOW_TEAM", "jam_detector", "run_lifelong"]

LANES = 4        # extra cost of a move against a one-way lane (measured: docs/lifelong.md)
ADMISSION_START = 0.04  # robots per free cell the run-time bound starts at (--admission on; measured there)
ADMISSION_DENSITY = 0.1  # robots per free cell from which (to ACTIVE_DENSITY) the run-time bound is on unless
                         # turned off, on maps that are not maps of aisles
# It falls only while robots pack in (over jam_least, and over ADMISSION_JAM_DENSITY times the robots per free
# cell: a dense team flowing packs more) and flow under target or 0.04 under their best since it last fell; the
# first fall goes at once to 0.7 of where it jammed, and it never grows past that again (a fall acts only as
# tasks end, hundreds of steps on a large map: GAME, docs/lifelong.md)
PURSUE_FRAC = 0.058  # robots per free cell that pursue their task, where the run-time bound would hold tasks on a
                     # map of ADMISSION_CELLS or more (every robot then holds one: pursuit.py; the 2024 winner's
                     # 2,500 of GAME's 6,500 robots on 43,151 free cells; measured on GAME, docs/lifelong.md)
ADMISSION_JAM = {"jam_factor": 2.0, "jam_least": 0.08, "drop": 0.04, "ceiling": 0.7}
ADMISSION_JAM_DENSITY = 0.5
ADMISSION_CELLS = 4000   # on maps of fewer free cells (short tasks: a crowd clears soon) the bound starts at ...
ADMISSION_SMALL_START = 0.5  # ... this share of the team, and grows as ADMISSION_SMALL says: x 1.25 a window while
ADMISSION_SMALL = {"slow_start": 1.25, "calm": 0.5,  # the packed share is under half a jam's (measured there),
                   "drop": None, "ceiling": None}  # and falls on target alone, with no ceiling: a fall acts soon
KEEP_RIGHT = 4   # extra cost of a move against the keep-right lane of a corridor 2 - 12 cells wide (measured there)
CROWD_W = 5.0    # scheduler's steps per robot crowding a task's errands beyond its share ...
CROWD_TEAM = 3000  # ... for teams of this size and more (measured: docs/lifelong.md)
HARD_FRAC = 0.7    # the share of the limit the step's hard mark starts at (a robot with a new goal and no row
                   # by then waits a step); it moves up while steps come back on time (budget.py)
GUIDE_DENSITY = 0.06  # robots per free cell from which guide paths lead (below: each robot's shortest way)
PACKED_DENSITY = 0.8  # robots per free cell from which a turning robot holds no second cell (claim_steps 0)
ACTIVE_FRAC = 0.3     # robots holding a task per free cell at most (the rest stand aside) ...
EPIBT_ACTIVE_FRAC = 0.43  # ... where EPIBT answers (350 of RANDOM-04's 819 free cells: docs/lifelong.md) ...
ACTIVE_DENSITY = 0.3  # ... in teams of this many robots per free cell or more
AISLE_ACTIVE_FRAC = 0.2   # ... and on maps of aisles: at least AISLE_SHARE of the free cells in one-cell corridor lanes
AISLE_JAM_CUT = 0.7       # on a map of aisles where no bound holds, once a jam is seen, at most this share of the
                          # robots then holding a task hold one until it clears (JamCut; measured: docs/lifelong.md)
AISLE_SHARE = 0.2
AISLE_LANES_JAM_LEAST = 0.25  # under the strong aisle lanes a jam's packed share is at least this (their teams
                              # setting out peak at 0.10 - 0.19 and flow; a jam under weak lanes passed 0.28)
WINDOW_TEAM = 1000    # EPIBT (+ LNS) leads in teams up to this size at any density (docs/lifelong.md) ...
WINDOW_DENSITY = 0.1  # ... and with EPIBT off, the windowed plan of operations from this to PACKED_DENSITY
CRISSCROSS_DENSITY = 0.02  # ... and from this in larger teams on a map that is not a map of aisles, over the
                           # crisscross graph (GAME's 6,500, CITY-01's 1,500 at 0.032: docs/lifelong.md)
EPIBT_DENSITY = 0.3   # robots per free cell from which EPIBT with LNS answers (MAPF_T) in any team ...
AISLE_EPIBT_DENSITY = 0.15  # ... (from this in teams over WINDOW_TEAM on a map of aisles: SORTATION's 10,000 at
                            # 0.18, docs/lifelong.md) ...
OPEN_LANES = 9        # ... and, on a map without corridors, every row and column is a lane (against: 1 + 9) ...
EPIBT_BIAS = 0.2      # ... and the lookahead takes its first step unless a rollout leads by this per robot
EPIBT_LNS_FRAC = 0.9  # ... and from EPIBT_DENSITY its LNS spends this share of the time to the step's deadline
SMALL_MAP_CELLS = 100  # on maps of fewer free cells a robot without progress for ...
SMALL_MAP_STUCK = 5     # ... this many steps yields its priority (EPIBT) and walks at random (PIBT), not 20: a
                        # dead end there is a few cells away (13 maps of 7 - 64 cells: docs/lifelong.md)
REPLAN_CORRIDORS = 0.5  # ... and where at least this share of the free cells has two free neighbours or fewer
                        # (corridors and dead ends), whole LaCAM plans answer (:mod:`.replan`; measured there) ...
REPLAN_DENSITY = 0.3    # ... if the map has a dead end, or the team is under this many robots per free cell: on
                        # loops without a dead end a denser team circulates better under EPIBT
RACE = {"start": 100, "window": 25, "settle": 5, "margin": 0.01, "hold": 400, "early": 5}   # EPIBT and PIBT
    # race while the run goes, the choice above answering first: from step 100 (after the team has spread out
    # from its starts, where a greedy method leads and then jams), in turns of 25 steps, the one ahead by 1 %
    # answering until the next race 400 steps later; a method 25 % behind is dropped after 5 scored steps;
    # in teams under EPIBT_DENSITY (measured on the held-out maps, RANDOM-04, WAREHOUSE: docs/results/lifelong.md)


def jam_detector(aisle_lanes: bool) -> JamDetector:
    """The :class:`~.admission.JamDetector` of a run; under the strong aisle lanes (``aisle_lanes``)
    a jam's packed share is at least :data:`AISLE_LANES_JAM_LEAST`. There a team setting out packs in
    up to 0.19 and then flows (WAREHOUSE's 10,000 robots: 0.177 at most in 5,000 steps; SORTATION's
    0.101), and the default mark, three times the first window's share, sat in that noise: it cut a
    flowing team in 3 of 4 runs of WAREHOUSE's first 1,000 steps, costing 15 % of the rate
    (docs/results/lifelong.md)."""
    return JamDetector(least=AISLE_LANES_JAM_LEAST) if aisle_lanes else JamDetector()


@dataclass
class RunResult:
    """The outcome of :func:`run_lifelong`: the simulator (with its output JSON), per-step
    planner times (ms), tasks finished after each step, and the CPU the process used in each
    step's scheduler + planner call (s, every thread: ``cpu_s / plan_ms * 1e3`` is the cores the
    step used)."""

    sim: Simulator
    plan_ms: np.ndarray
    finished: np.ndarray
    wall_s: float
    stats: dict = field(default_factory=dict)
    cpu_s: np.ndarray | None = None

    def summary(self) -> dict:
        """Tasks finished, timeouts, invalid steps, planner ms p50/p99/max, and the cores the
        planner used: its CPU time over its wall time, over the run (``cores``) and the median step's
        (``cores_p50``)."""
        ms = self.plan_ms if len(self.plan_ms) else np.zeros(1)
        cores = {}
        if self.cpu_s is not None and len(self.plan_ms):
            wall = np.maximum(self.plan_ms / 1e3, 1e-9)
            cores = {"cores": round(float(self.cpu_s.sum() / wall.sum()), 3),
                     "cores_p50": round(float(np.median(self.cpu_s / wall)), 3)}
        return {"steps": self.sim.t, "tasks_finished": self.sim.finished, "timeouts": self.sim.timeouts,
                "invalid_steps": self.sim.invalid_steps, "schedule_errors": len(self.sim.schedule_errors),
                "plan_ms_p50": float(np.percentile(ms, 50)), "plan_ms_p99": float(np.percentile(ms, 99)),
                "plan_ms_max": float(ms.max()), "wall_s": self.wall_s, **cores, **self.stats}


def run_lifelong(problem: LorrProblem, steps: int, plan_time_limit_ms: float = 1000.0, seed: int = 0,
                 scheduler: str = "batch", model: str = MAPF_T, budget_frac: float | None = None,
                 cache_bytes: int | None = None, lanes: int | None = None, crowd_w: float | None = None,
                 record: bool = True, guide: bool | None = None, planner_kw: dict | None = None,
                 flow_kw: dict | None = None, max_active: int | None = None, open_lanes: int | None = None,
                 keep_right: int | None = None, admission: bool | None = None, admission_kw: dict | None = None,
                 replan: bool | None = None, race: bool | None = None, race_kw: dict | None = None,
                 length_w: float | None = None, pursue: int | None = None,
                 progress: Callable[[int, int, float], None] | None = None) -> RunResult:
    """Run ``problem`` for ``steps`` time steps under the rules (:mod:`.simulator`).

    plan_time_limit_ms: the per-step limit (ms) of scheduler + planner; budget_frac: the step's
    deadline as a share of the limit, fixed (``hard`` then at 0.7); None (default): both marks measured
    while the run goes (:class:`~.budget.StepBudget`; ``stats["budget"]`` gives their history); scheduler:
    ``"batch"`` (default, the better measured) or ``"greedy"``; model: ``"MAPF_T"`` or
    ``"MAPF"``; cache_bytes: the bound of the distance maps (default
    :func:`~.distances.cache_bytes_for` the team and the machine's available memory); lanes:
    the extra cost of a move against a one-way lane (:func:`~.guidance.lane_costs`; 0: none;
    None (default): ``LANES``, and ``OPEN_LANES`` where EPIBT answers a team over ``WINDOW_TEAM`` on
    a map of aisles, whose lanes then lead in place of guide paths, as the 2024 winner's guidance
    graph on its warehouses: measured on WAREHOUSE, docs/lifelong.md);
    crowd_w: the scheduler's cost per robot crowding a task's errands (default
    ``CROWD_W`` for teams of ``CROWD_TEAM`` robots or more, else 0);
    guide: robots follow traffic-flow guide paths (:class:`~.flow.TrafficFlow`); None (default): when
    the team has at least ``GUIDE_DENSITY`` robots per free cell (on sparser teams the detours they
    ask for cost more than the jams they avoid: docs/lifelong.md); from ``PACKED_DENSITY`` robots per
    free cell a robot that turns towards a cell does not hold it (``claim_steps=0``; measured there);
    in teams up to ``WINDOW_TEAM`` robots, from ``EPIBT_DENSITY`` robots per free cell in any team,
    and in larger teams from ``CRISSCROSS_DENSITY`` on a map that is not a map of
    aisles (below) and from ``AISLE_EPIBT_DENSITY`` on a map of aisles, the planner answers
    with EPIBT and LNS (:mod:`.epibt`; ``planner_kw={"epibt": False}`` turns it off, and then from
    ``WINDOW_DENSITY`` to ``PACKED_DENSITY`` in teams up to ``WINDOW_TEAM`` the
    windowed plan of operations refined by LNS takes its place: :mod:`.window`,
    ``planner_kw={"ops": False}`` turns that off too), its first step taken
    unless a PIBT rollout brings the robots closer by ``EPIBT_BIAS`` steps per robot with a goal
    (``planner_kw={"window_bias": ...}``), and from ``EPIBT_DENSITY`` (``AISLE_EPIBT_DENSITY`` in larger
    teams on a map of aisles) its LNS spends
    ``EPIBT_LNS_FRAC`` of the time to the step's deadline, the rollouts the rest
    (``planner_kw={"lns_frac": ...}``); open_lanes: on a map
    without corridor lanes, every row and column becomes a lane with this extra cost against it
    (None: ``OPEN_LANES`` under EPIBT, else 0); keep_right: the extra cost of a move against the
    keep-right lane of a corridor 2 - 12 cells wide (:func:`~.guidance.keep_right_costs`; None:
    ``KEEP_RIGHT``, 0: none). Where EPIBT answers a team over ``WINDOW_TEAM`` below
    ``EPIBT_DENSITY`` (a map that is not a map of aisles), every row and column is a lane, corridors
    or not, in place of guide paths and keep-right lanes (guide, keep_right None: off), as the 2024
    winner's grid guidance on GAME and CITY (measured on GAME: docs/lifelong.md);
    max_active: at most this many robots hold a task; None (default):
    ``ACTIVE_FRAC`` of the free cells from ``ACTIVE_DENSITY`` robots per free cell
    (``EPIBT_ACTIVE_FRAC`` where EPIBT answers), 0: no bound;
    ``AISLE_ACTIVE_FRAC`` instead on a map of aisles (at least ``AISLE_SHARE`` of its free cells in
    one-cell corridor lanes, as a warehouse's shelves and a sortation centre's chutes make them), and
    below ``ACTIVE_DENSITY`` there, once the jam detector (below) sees a jam, ``AISLE_JAM_CUT`` of
    the robots then holding a task, grown back as the jam clears (:class:`~.admission.JamCut`;
    ``stats["jam_cut"]`` the first cut's bound, ``stats["jam_bounds"]`` every (step, bound); not under
    whole plans, which bring every robot to its goal; measured in docs/lifelong.md);
    admission: where no ``max_active`` bound holds, the bound is set at run time by the share of
    robots with a task that move and the share packed in (:class:`~.admission.FlowAdmission` with
    ``ADMISSION_JAM``, its least packed share at least ``ADMISSION_JAM_DENSITY`` times the robots per
    free cell, and ``admission_kw``; from ``ADMISSION_START`` robots per free cell, or on maps of fewer
    than ``ADMISSION_CELLS`` free cells from ``ADMISSION_SMALL_START`` of the team, with
    ``ADMISSION_SMALL``); None (default): on from ``ADMISSION_DENSITY`` robots per free cell on maps
    that are not maps of aisles (measured in docs/lifelong.md), else off;
    on maps of fewer than ``SMALL_MAP_CELLS`` free cells a robot without progress for
    ``SMALL_MAP_STUCK`` steps yields its priority under EPIBT and walks at random under PIBT (20
    steps elsewhere: :class:`~.pibt.PIBTPlanner`'s ``yield_steps`` and ``stuck_steps``), and from
    ``EPIBT_DENSITY`` robots per free cell (``AISLE_EPIBT_DENSITY``, as above) on larger maps none yields;
    replan: whole LaCAM plans answer each step, planned again at every goal change and executed under
    turns in the plan's order (:class:`~.replan.ReplanPlanner`, the planner above its fallback); None
    (default): on maps of fewer than ``SMALL_MAP_CELLS`` free cells of which at least
    ``REPLAN_CORRIDORS`` have two free neighbours or fewer (corridors and dead ends), if the map has
    a dead end or the team is under ``REPLAN_DENSITY`` robots per free cell, MAPF_T only;
    race: EPIBT and PIBT take turns in windows and the one whose robots make the more progress
    to their goals answers until the next race (:class:`~.race.MethodRace` with ``RACE`` updated by
    ``race_kw``; the choice above answers first), each with its own settings above and, where
    ``ACTIVE_FRAC`` bounds the robots holding a task, its own bound once the race has chosen it (a
    turn keeps the bound of the method chosen before: tasks taken back for a turn and given again
    are travel lost); ``stats["race"]`` lists the races. Not under whole plans, MAPF, or a
    ``planner_kw`` that names ``epibt``; None (default): on under ``EPIBT_DENSITY`` robots per free
    cell (denser teams made half EPIBT's progress under PIBT in every race, and a race cost RANDOM-04
    5 % of its tasks), False: the choice above answers throughout; whether it races or not,
    ``stats["progress_per_step"]`` gives the robots' progress to their goals a step, the race's
    score (:func:`~.race.progress`; 0 under whole plans);
    length_w: the share of a task's own length (first errand to last) in its cost to a robot, beside
    the way to its first errand (:attr:`~.scheduler.Scheduler.length_w`); None (default): the
    scheduler's;
    pursue: every robot may hold a task, and each step only this many, those with the fewest steps left
    to the end of theirs, pursue it; the others stand aside (:mod:`.pursuit`, the 2024 winner's rule;
    ``stats["pursue"]``); None (default): ``PURSUE_FRAC`` of the free cells where the run-time bound
    would be on (below) on a map of ``ADMISSION_CELLS`` free cells or more, in its place (a bound on
    the robots pursuing acts at the next step, one on those holding a task only as opened tasks end),
    else 0: off. Raises ValueError for a negative count, or one beside ``max_active`` or ``admission``;
    progress: called after each step with (step, tasks finished, planner ms).
    Where no bound holds, a :class:`~.admission.JamDetector` watches the share of the robots with a
    task that are packed in; ``stats`` give its ``packed_shares`` (per 25 steps) and ``jam_at``,
    the step a jam was first seen (None: none); on a map of aisles the bound is then cut, and lifted
    as the jam clears (``max_active`` is the bound at the end).
    Compilation happens before step 0 (:func:`~.kernels.warm_up`). Raises ValueError for a
    bad scheduler or model name, MemoryError when the maps of the team do not fit.
    """
    grid = problem.grid
    n_free = max(1, len(grid.free_cells()))
    density = problem.team_size / n_free
    small = problem.team_size <= WINDOW_TEAM
    corridors = lane_costs(grid, 1)     # > 1 where a move goes against a one-way corridor lane
    aisles = float((corridors > 1).any(axis=1).sum()) / n_free     # share of free cells in one-cell lanes
    aisle_map = aisles >= AISLE_SHARE
    dense_from = AISLE_EPIBT_DENSITY if aisle_map and not small else EPIBT_DENSITY
    if density >= PACKED_DENSITY:       # the cell a turning robot would hold is the one the others need
        planner_kw = {"claim_steps": 0, **(planner_kw or {})}
    if n_free < SMALL_MAP_CELLS:
        planner_kw = {"yield_steps": SMALL_MAP_STUCK, "stuck_steps": SMALL_MAP_STUCK, **(planner_kw or {})}
        if replan is None:              # mostly corridors, with a dead end or a sparse team: whole plans
            degree = (grid.nbr[grid.free_cells()] >= 0).sum(axis=1)
            replan = (float((degree <= 2).mean()) >= REPLAN_CORRIDORS
                      and (bool((degree == 1).any()) or density < REPLAN_DENSITY))
    elif density >= dense_from:         # a dense team: robots wait in crowds, and yielding cost (docs/lifelong.md)
        planner_kw = {"yield_steps": 0, **(planner_kw or {})}
    epibt = (model == MAPF_T
             and (small or density >= (dense_from if aisle_map else CRISSCROSS_DENSITY))
             and (planner_kw or {}).get("epibt", True))
    crisscross = epibt and not small and not aisle_map and density < EPIBT_DENSITY    # the winner's grid
    aisle_lanes = epibt and not small and aisle_map     # the corridors' lanes lead, strong as the winner's
    if lanes is None:
        lanes = OPEN_LANES if aisle_lanes else LANES
    cost = lane_costs(grid, lanes) if lanes else None
    if guide is None:
        guide = density >= GUIDE_DENSITY and not crisscross and not aisle_lanes
    user_kw = dict(planner_kw or {})
    # each method's own settings, as the constants above would set them for it
    arms = {"epibt": {"epibt": True, "ops": False, "window_bias": EPIBT_BIAS,
                      "lns_frac": EPIBT_LNS_FRAC if density >= dense_from else 0.5},
            "pibt": {"epibt": False, "ops": model == MAPF_T and WINDOW_DENSITY <= density < PACKED_DENSITY and small,
                     "window_bias": 0.0, "lns_frac": 0.5}}
    planner_kw = {**arms["epibt" if epibt else "pibt"], **(planner_kw or {})}
    if cache_bytes is None:
        cache_bytes = cache_bytes_for(grid, problem.team_size)
    warm_up()
    window_warm_up()
    race = bool((density < EPIBT_DENSITY if race is None else race)
                and model == MAPF_T and not replan and "epibt" not in user_kw)
    if epibt or race:
        epibt_warm_up()
    if guide:
        flow_warm_up()
    t_start = time.perf_counter()
    check_pursue(pursue, max_active, admission)
    auto = admission is None and density >= ADMISSION_DENSITY
    if pursue is None:
        pursue = (int(PURSUE_FRAC * n_free) if auto and not aisle_map and n_free >= ADMISSION_CELLS
                  and max_active is None and density < ACTIVE_DENSITY else 0)
    arm_active = {}
    if max_active is None and density >= ACTIVE_DENSITY and not pursue:
        arm_active = {"epibt": int((AISLE_ACTIVE_FRAC if aisle_map else EPIBT_ACTIVE_FRAC) * n_free),
                      "pibt": int((AISLE_ACTIVE_FRAC if aisle_map else ACTIVE_FRAC) * n_free)}
        max_active = arm_active["epibt" if epibt else "pibt"]
    if pursue:
        admission = False
    if admission is None:
        admission = auto and not aisle_map
    if open_lanes is None:
        open_lanes = OPEN_LANES if epibt and lanes else 0
    if open_lanes and (crisscross or cost is None or (cost == 1).all()):    # the crisscross everywhere
        cost = lane_costs(grid, open_lanes, everywhere=True)
    if keep_right is None:
        keep_right = 0 if crisscross else KEEP_RIGHT
    if keep_right:
        cost = keep_right_costs(grid, keep_right, cost=cost)
    cache = DistanceCache(grid, max_bytes=cache_bytes, cost=cost)
    if crowd_w is None:
        crowd_w = CROWD_W if problem.team_size >= CROWD_TEAM else 0.0
    sched = make_scheduler(scheduler, cache, crowd_w, length_w)
    if max_active is not None and max_active > 0:
        sched.max_active = max_active
    flow = None
    if guide:
        kw = {"turn": int(model == MAPF_T), **(flow_kw or {})}
        flow = TrafficFlow(grid, cache, problem.team_size, cost=cache.cost, seed_=seed, **kw)
    planner = PIBTPlanner(grid, cache, model=model, seed=seed, flow=flow, **(planner_kw or {}))
    step_planner = planner
    replan = bool(replan and model == MAPF_T)
    chooser = None
    if race:
        chooser = MethodRace(list(arms), first=0 if epibt else 1, **{**RACE, **(race_kw or {})})
        arms = {a: {k: v for k, v in kw.items() if k not in user_kw} for a, kw in arms.items()}
    answering = "epibt" if epibt else "pibt"
    if replan:
        refine_warm_up()
        step_planner = ReplanPlanner(grid, planner, seed=seed)
    sim = Simulator(grid, problem.starts, problem.tasks, problem.reveal, model=model, record=record)
    limit = plan_time_limit_ms / 1e3
    budget = StepBudget(limit, hard=HARD_FRAC) if budget_frac is None else None
    deadline_frac, hard_frac = (budget.deadline, budget.hard) if budget is not None else (budget_frac, HARD_FRAC)
    plan_ms = np.zeros(steps)
    cpu_s = np.zeros(steps)
    finished = np.zeros(steps, dtype=np.int64)
    sched_ms = 0.0
    progress_sum = 0.0
    control = None
    if admission and sched.max_active is None:
        ctl_kw = {**ADMISSION_JAM, "start": int(ADMISSION_START * n_free),
                  "jam_least": max(ADMISSION_JAM["jam_least"], ADMISSION_JAM_DENSITY * density)}
        if n_free < ADMISSION_CELLS:
            ctl_kw.update(ADMISSION_SMALL, start=int(ADMISSION_SMALL_START * problem.team_size))
        control = FlowAdmission(problem.team_size, **{**ctl_kw, **(admission_kw or {})})
    detector = jam_detector(aisle_lanes) if control is None and sched.max_active is None else None
    guard = (JamCut(detector, problem.team_size, cut=AISLE_JAM_CUT)
             if detector is not None and aisle_map and max_active is None and not replan and not pursue else None)
    watch = detector is not None or (control is not None and control.jam_factor is not None)
    occupied = np.zeros(grid.n_cells + 1, dtype=bool) if watch else None
    for k in range(steps):
        c0, t0 = time.process_time(), time.perf_counter()
        deadline = t0 + deadline_frac * limit
        prop = sched.schedule(sim.pos, sim.assignment, sim.pool.open, sim.t, t0 + 0.5 * deadline_frac * limit)
        t1 = time.perf_counter()
        goals = np.full(sim.n, -1, dtype=np.int64)
        has = np.flatnonzero(prop >= 0)
        if len(has):
            open_ = sim.pool.open
            goals[has] = [open_[int(prop[a])].goal for a in has]
        if pursue:
            go = pursuing(steps_left(sim.pos, prop, sim.pool.open, cache), pursue)
            goals[~go] = -1
        if chooser is not None:
            if chooser.arm() != answering:
                answering = chooser.arm()
                for key, value in arms[answering].items():
                    setattr(planner, key, value)
            chosen = chooser.arms[chooser.current]      # the bound follows the race's choice, not its turns
            if arm_active and sched.max_active == arm_active["pibt" if chosen == "epibt" else "epibt"]:
                sched.max_active = arm_active[chosen]
        p_plan = sim.pos.copy()         # where the robots were: the step's progress, and who moved
        actions = step_planner.plan(sim.pos, sim.head, goals, deadline, t0 + hard_frac * limit)
        dt = time.perf_counter() - t0
        cpu_s[k] = time.process_time() - c0
        sched_ms += (t1 - t0) * 1e3
        if budget is not None:
            budget.observe(dt / limit)
            deadline_frac, hard_frac = budget.deadline, budget.hard
        sim.step(actions, prop, plan_time_s=dt, timed_out=dt > limit)
        held = go if pursue else prop >= 0
        n_packed = 0
        if watch:
            occupied[:] = False
            occupied[sim.pos] = True
            n_packed = int(packed(grid.nbr, sim.pos[held], occupied).sum())
        if guard is not None:
            sched.max_active = guard.observe(k, n_packed, int(held.sum()))
        elif detector is not None:
            detector.observe(k, n_packed, int(held.sum()))
        if control is not None:
            sched.max_active = control.observe(k, int((held & (sim.pos != p_plan)).sum()), int(held.sum()),
                                               n_packed)
        moved = race_progress(cache.table, planner.last_slot, p_plan, sim.pos) if not replan else 0.0
        progress_sum += moved
        if chooser is not None:
            chooser.observe(moved)
        plan_ms[k] = dt * 1e3
        finished[k] = sim.finished
        if progress is not None:
            progress(k + 1, sim.finished, dt * 1e3)
    stats = {"scheduler": scheduler, "max_active": getattr(sched, "max_active", None), "lanes": lanes,
             "aisles": round(aisles, 3), "aisle_map": aisle_map, "aisle_lanes": aisle_lanes,
             "keep_right": keep_right, "crisscross": crisscross,
             "crowd_w": crowd_w, "length_w": sched.length_w, "guide": guide, "epibt": epibt, "open_lanes": open_lanes,
             "window_bias": planner.window_bias, "replan": replan, "yield_steps": planner.yield_steps,
             "stuck_steps": planner.stuck_steps,
             "claim_steps": planner.claim_steps, "scheduler_ms_total": sched_ms,
             **planner.stats, **(step_planner.stats if step_planner is not planner else {}),
             **(planner._window.stats if planner._window is not None else {}),
             **(planner._epibt.stats if planner._epibt is not None else {}),
             **(flow.stats if flow is not None else {}),
             "shed": sched.shed + getattr(getattr(sched, "_greedy", None), "shed", 0),
             "progress_per_step": round(progress_sum / max(1, steps), 3),
             "race": ({"history": chooser.history, "switches": chooser.switches, "last": answering}
                      if chooser is not None else None),
             "pursue": pursue,
             "admission_on": control is not None,
             "admission": control.decisions if control is not None else None,
             "jam_at": detector.jam_at if detector is not None else None,
             "jam_cut": guard.changes[0][1] if guard is not None and guard.changes else None,
             "jam_bounds": guard.changes if guard is not None else None,
             "packed_shares": detector.shares if detector is not None else None,
             "distance_maps": cache.computed, "maps_evicted": cache.evicted, "cache_rows": cache.capacity,
             "cache_rows_used": len(cache),
             "budget": ({"hard": budget.hard, "falls": budget.falls, "history": budget.history} if budget is not None
                        else {"deadline": budget_frac, "hard": HARD_FRAC})}
    return RunResult(sim, plan_ms, finished, time.perf_counter() - t_start, stats, cpu_s)


def rich_progress(total: int, label: str = "lifelong"):
    """A context manager yielding a ``progress(step, finished, ms)`` callback that shows a
    rich progress bar (steps, tasks finished, planner ms) on stderr."""
    from contextlib import contextmanager

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    @contextmanager
    def _cm():
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("tasks {task.fields[done]}  planner {task.fields[ms]:.0f} ms"),
                      TimeRemainingColumn(), console=Console(file=sys.stderr), transient=False) as p:
            tid = p.add_task(label, total=total, done=0, ms=0.0)

            def cb(step: int, done: int, ms: float) -> None:
                p.update(tid, completed=step, done=done, ms=ms)
            yield cb
    return _cm()
