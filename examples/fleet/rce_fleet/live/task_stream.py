"""A lifelong run of the live fleet (``rce-fleet demo --lifelong``): the generated task stream
and the numbers a warehouse manager reads in its report.

- :class:`TaskStream`: tasks arriving as a Poisson process of ``rate_per_min`` per simulated
  minute, each a pick-up station then a drop-off station drawn at random (seeded) from the
  places (or the drop-off nearest the pick-up, ``nearest_drop``), after ``backlog`` tasks waiting
  at the start; :meth:`TaskStream.times_and_errands` is the stream itself, so the offline
  prediction (``bench/fleet_live.py``) replays the very same tasks.
- :func:`tasks_section`: the report's ``tasks`` section from the fleet's newest
  ``fleet/TaskList``: done, failed, cancelled, per_hour, mean_s, p95_s, deadline_missed, and
  ``failed_reasons`` (reason -> count, over the failed tasks the list still shows), and ``list``: the
  tasks the list shows (the open ones and the newest closed ones: id, state, robot, errands, and
  the fleet times it was created and finished).
- :func:`robot_section`: per robot, ``utilisation`` (share of its time on a task),
  ``distance_m``, ``battery_min_pct`` and ``charges`` (simulator ground truth where there is one),
  ``tasks_done`` and ``stalls`` (the dispatcher's stall alerts).
- :func:`goal_motion_delays`: sim s from each task's assignment to its robot's first motion
  after it (robots that were standing when they got the task).
"""
from __future__ import annotations

import bisect
import math
import random

from ..operations.places import Places

__all__ = ["TaskStream", "goal_motion_delays", "robot_section", "tasks_section"]


class TaskStream:
    """Pick-up -> drop-off tasks at ``rate_per_min`` per simulated minute (Poisson, ``seed``), after
    ``backlog`` tasks that wait at the start (time 0: the orders a shift begins with). Each drop-off is
    drawn at random, or with ``nearest_drop`` it is the drop-off nearest the pick-up (steps on the
    places' grid; the first by name on a tie). Raises ValueError when the places have no pick-up or
    no drop-off station, the rate is not > 0 or the backlog < 0."""

    def __init__(self, places: Places, rate_per_min: float, seed: int = 1, *, backlog: int = 0,
                 nearest_drop: bool = False):
        self.picks, self.drops = [p.name for p in places.of_kind("pickup")], [p.name for p in places.of_kind("dropoff")]
        if not self.picks or not self.drops:
            raise ValueError("generated tasks need pick-up and drop-off places (--places)")
        if not rate_per_min > 0:
            raise ValueError(f"task rate must be > 0 per minute, got {rate_per_min}")
        if backlog < 0:
            raise ValueError(f"the backlog must be >= 0 tasks, got {backlog}")
        self.rate, self.seed, self.backlog = rate_per_min, seed, int(backlog)
        self.drop_of = _nearest_drops(places) if nearest_drop else None

    def times_and_errands(self, duration_s: float) -> list[tuple[float, list[str]]]:
        """(s after the start, [pick-up, drop-off]) for every task waiting at the start or arriving within
        ``duration_s``."""
        rng = random.Random(self.seed)
        out, t = [], 0.0

        def errands() -> list[str]:
            pick = rng.choice(self.picks)
            return [pick, self.drop_of[pick] if self.drop_of else rng.choice(self.drops)]
        out += [(0.0, errands()) for _ in range(self.backlog)]
        while True:
            t += rng.expovariate(self.rate / 60.0)
            if t >= duration_s:
                return out
            out.append((t, errands()))


def _nearest_drops(places: Places) -> dict[str, str]:
    """Pick-up name -> the name of the drop-off fewest steps from it on the places' grid (breadth-first
    over the free cells; a pick-up that reaches none gets the first by name)."""
    geo = places.geo
    drops = {p.cell: p.name for p in places.of_kind("dropoff")}
    out = {}
    for pick in places.of_kind("pickup"):
        seen, ring, found = {pick.cell}, [pick.cell], None
        while ring and found is None:
            found = min((drops[c] for c in ring if c in drops), default=None)
            ring = sorted({n for c in ring for n in geo.neighbours(c) if geo.is_free(n) and n not in seen})
            seen.update(ring)
        out[pick.name] = found or min(drops.values())
    return out


def _percentile(xs: list[float], q: float) -> float:
    if not xs:
        return 0.0
    s = sorted(xs)
    return s[min(len(s) - 1, max(0, math.ceil(q * len(s)) - 1))]


def tasks_section(task_list: dict | None, duration_s: float, generated: int = 0) -> dict:
    """The report's ``tasks`` section (module docstring) over ``duration_s`` simulated s."""
    tl = task_list or {}
    done = int(tl.get("done", 0))
    reasons: dict[str, int] = {}
    for t in tl.get("tasks", []):
        if t.get("state") == "failed":
            reasons[t.get("reason", "")] = reasons.get(t.get("reason", ""), 0) + 1
    return {"done": done, "failed": int(tl.get("failed", 0)), "cancelled": int(tl.get("cancelled", 0)),
            "per_hour": round(done * 3600.0 / duration_s, 2) if duration_s > 0 else 0.0,
            "mean_s": round(float(tl.get("mean_s", 0.0)), 2), "p95_s": round(float(tl.get("p95_s", 0.0)), 2),
            "deadline_missed": int(tl.get("deadline_missed", 0)), "queued": int(tl.get("queued", 0)),
            "generated": generated, "failed_reasons": reasons,
            "list": [{k: t.get(k) for k in ("id", "state", "robot", "errands", "created", "finished", "reason")}
                     for t in tl.get("tasks", [])]}


def robot_section(task_list: dict | None, sim) -> dict[str, dict]:
    """Per robot: utilisation, distance_m, battery_min_pct, charges (module docstring)."""
    work = {r["robot"]: r for r in (task_list or {}).get("robots", [])}
    out = {}
    for name, bot in (sim.bots.items() if sim else []):
        w = work.get(name, {})
        since = float(w.get("since_s", 0.0))
        b = bot.battery
        out[name] = {"utilisation": round(float(w.get("busy_s", 0.0)) / since, 4) if since > 0 else 0.0,
                     "distance_m": round(bot.distance, 2),
                     "battery_min_pct": round(100.0 * b.min_wh / b.params.capacity_wh, 2) if b else None,
                     "charges": b.charges if b else 0, "ran_flat": bool(b and b.flat),
                     "tasks_done": int(w.get("tasks_done", 0)), "stalls": int(w.get("stalls", 0))}
    return out


def goal_motion_delays(task_list: dict | None, sim) -> list[float]:
    """Sim s from each shown task's assignment to its robot's next motion start (module docstring)."""
    out = []
    for t in (task_list or {}).get("tasks", []):
        bot = sim.bots.get(t.get("robot", "")) if sim else None
        at = float(t.get("assigned", 0.0))
        if bot is None or at <= 0:
            continue
        starts = bot.motion_starts
        i = bisect.bisect_left(starts, at)
        standing = i == bisect.bisect_left(bot.motion_stops, at)
        if standing and i < len(starts):
            out.append(starts[i] - at)
    return out
