"""Resource use of process trees (psutil) and CPU rates between two looks.

:func:`measure` sums CPU time, resident memory and process count over a set of pids;
:class:`CpuRate` turns successive CPU-time readings into a percentage of one core (100 = one
core busy) over the interval since the previous reading of the same key (or, on the first
reading, since the thing started)."""
from __future__ import annotations

import time

import psutil


def tree(pid: int | None) -> list[int]:
    """``pid`` and every descendant of it (host pids); [] if it is gone."""
    if not pid:
        return []
    try:
        p = psutil.Process(pid)
        return [pid, *(c.pid for c in p.children(recursive=True))]
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return []


def measure(pids: list[int]) -> dict:
    """``{cpu_seconds, rss_bytes, processes}`` summed over ``pids`` (zombies and vanished
    processes count for nothing)."""
    cpu = rss = n = 0
    for pid in set(pids):
        try:
            p = psutil.Process(pid)
            with p.oneshot():
                if p.status() == psutil.STATUS_ZOMBIE:
                    continue
                t = p.cpu_times()
                cpu += t.user + t.system
                rss += p.memory_info().rss
                n += 1
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return {"cpu_seconds": cpu, "rss_bytes": rss, "processes": n}


class CpuRate:
    """Per-key CPU percentage between readings."""

    MIN_INTERVAL = 0.25   # s

    def __init__(self) -> None:
        self._last: dict = {}

    def percent(self, key, cpu_seconds: float, started: float | None = None) -> float:
        """CPU % of ``key`` since its previous reading; on the first reading, since ``started``
        (a ``time.monotonic()`` value), else 0. Readings closer than ``MIN_INTERVAL`` s to the
        previous one repeat its value (two callers polling at once do not see noise). Never
        negative (processes that exited take their CPU time with them)."""
        now = time.monotonic()
        prev = self._last.get(key)
        if prev is None:
            pct = 0.0
            if started is not None and now - started >= 1e-3:
                pct = max(0.0, 100.0 * cpu_seconds / (now - started))
        else:
            dt = now - prev[0]
            if dt < self.MIN_INTERVAL:
                return prev[2]
            pct = max(0.0, 100.0 * (cpu_seconds - prev[1]) / dt)
        self._last[key] = (now, cpu_seconds, pct)
        return pct

    def forget(self, key) -> None:
        self._last.pop(key, None)
