"""Which robots pursue their task this step: every robot may hold a task, and only those nearest
its end go for it; the others stand aside (no goal this step: they move as a robot without a task
does, and may be pushed; held still instead, they finished no more: docs/results/lifelong.md).

A bound on the robots *holding* a task acts only as tasks end, since an opened task is never taken
back (the League of Robot Runners' rule); on a large map that is hundreds of steps, while a jam at
the corridor mouths grows over as many (:mod:`.admission`). A bound on the robots *pursuing* their
task acts at the next step, and the scheduler matches every robot against the open tasks, so each
task goes to the robot nearest it. Those nearest the end of their task go first: they finish soonest,
and free their place for the next. This is the 2024 League winner's rule (team No_Man's_Sky,
github.com/Straple/LORR24, ``robot_handler.cpp``: every step the robots are ordered by the steps
left to the end of their task, and the first ``n - disable_agents`` plan towards it).
"""
from __future__ import annotations

import numpy as np

from .distances import DistanceCache
from .tasks import Task

__all__ = ["check_pursue", "pursuing", "steps_left"]


def check_pursue(pursue: int | None, max_active: int | None = None, admission: bool | None = None) -> None:
    """Raise ValueError unless ``pursue`` (robots pursuing their task; None: the default) is 0 or more,
    and, above 0, comes without another bound (``max_active``, ``admission`` on) beside it."""
    if pursue is not None and pursue < 0:
        raise ValueError(f"the robots pursuing their task cannot be negative, got {pursue}")
    if pursue and (max_active or admission):
        raise ValueError("a bound on the robots pursuing a task takes no max_active or admission beside it")


def _rest(tk: Task, cache: DistanceCache) -> list[int]:
    """``rest[i]``: steps from errand ``i`` of ``tk`` through its last (cached in ``tk.extra``;
    the pairs' distances along ``cache``'s costs)."""
    rest = tk.extra.get("rest")
    if rest is None:
        e = tk.errands
        rest = [0] * len(e)
        for i in range(len(e) - 2, -1, -1):
            rest[i] = rest[i + 1] + cache.dist(e[i], e[i + 1])
        tk.extra["rest"] = rest
    return rest


def steps_left(pos: np.ndarray, prop: np.ndarray, tasks: dict[int, Task], cache: DistanceCache) -> np.ndarray:
    """(n,) steps each robot has left to the end of its task: to its next errand (its distance map if
    ``cache`` has it, else Manhattan), then through the task's later errands; inf for a robot without a
    task (``prop`` -1). ``pos``: (n,) cells; ``prop``: (n,) task ids."""
    left = np.full(len(pos), np.inf)
    cols = cache.grid.cols
    for a in np.flatnonzero(prop >= 0).tolist():
        tk = tasks[int(prop[a])]
        g, p = tk.goal, int(pos[a])
        s = cache.cached(g)
        if s >= 0:
            to = float(cache.table[s, p])
        else:
            to = float(abs(g // cols - p // cols) + abs(g % cols - p % cols))
        left[a] = to + _rest(tk, cache)[tk.next_errand]
    return left


def pursuing(left: np.ndarray, k: int) -> np.ndarray:
    """(n,) bool: the ``k`` robots with the fewest steps ``left`` (finite: holding a task) pursue it;
    all holders when fewer than ``k`` hold one. Ties go to the lower index. Raises ValueError for
    ``k`` < 0."""
    if k < 0:
        raise ValueError(f"the robots pursuing their task cannot be negative, got {k}")
    holders = np.isfinite(left)
    if holders.sum() <= k:
        return holders
    out = np.zeros(len(left), dtype=bool)
    out[np.argsort(left, kind="stable")[:k]] = True
    return out
