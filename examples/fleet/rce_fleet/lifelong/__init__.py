"""rce_fleet.lifelong: a fleet that runs by tasks without end, under a time budget per step
(sans-I/O: plain classes, no sockets).

- :mod:`.grid`: the map, headings and move table.
- :mod:`.lorr`: League of Robot Runners 2024 problem files.
- :mod:`.tasks`: tasks (ordered errands, priority, time window) and their states.
- :mod:`.distances`: per-goal breadth-first distance maps, LRU-bounded.
- :mod:`.scheduler`: task allocation (auction on finish time; batch assignment).
- :mod:`.kernels`: the compiled hot loops (numba).
- :mod:`.pibt`: the lifelong PIBT planner and one-shot PIBT.
- :mod:`.simulator`: the rules (actions, conflicts, timeouts, reveals, errands) and the
  start-kit's output JSON.
- :mod:`.runner`: a whole run with progress, as ``rce-fleet lifelong`` does it.
"""
from .distances import DistanceCache
from .grid import LifelongGrid
from .lorr import LorrProblem, ProblemError, load_lorr_map, load_problem
from .pibt import PIBTPlanner, solve_one_shot
from .scheduler import BatchScheduler, GreedyScheduler, make_scheduler
from .simulator import MAPF, MAPF_T, Simulator, check_actions, replay
from .tasks import Task, TaskError, TaskPool, TaskState

__all__ = [
    "MAPF", "MAPF_T", "BatchScheduler", "DistanceCache", "GreedyScheduler", "LifelongGrid", "LorrProblem",
    "PIBTPlanner", "ProblemError", "Simulator", "Task", "TaskError", "TaskPool", "TaskState", "check_actions",
    "load_lorr_map", "load_problem", "make_scheduler", "replay", "solve_one_shot",
]
