"""lacam3 (Okumura, "Engineering LaCAM*", AAMAS-24; github.com/Kei18/lacam3) as a peer of
rce's one-shot planner, run on the same instance in the same benchmark run.

lacam3 is not shipped with rce: build it from its repository (``cmake -B build
-DCMAKE_BUILD_TYPE=Release && make -C build``) and pass its ``main`` to
``bench/planner.py --lacam3 PATH``. It reads a MovingAI octile map and a version-1 scenario
(movingai.com/benchmarks/formats.html), which this module writes from rce's grid, and writes
``key=value`` lines (``soc``, ``soc_lb``, ``sum_of_loss``, ``makespan``, ``comp_time`` and
``comp_time_initial_solution`` in ms, ``cost_initial_solution``: the first solution's sum of
loss, ``solved``).

lacam3's time limit (``-t``, whole seconds) is wall-clock; it runs 10 PIBT threads per search
step and 4 refiner threads after the first solution, so on a 2-core machine it uses both cores.
Its ``soc`` is the sum of the agents' last arrivals at their goals (rce's sum of costs); its own
objective is the sum of loss (steps not waiting at the goal), which is lower when agents are
pushed off goals they have reached.
"""
from __future__ import annotations

import math
import subprocess
import tempfile
import time
from pathlib import Path

__all__ = ["run_lacam3"]


def _write_instance(d: Path, free, agents: list[tuple[int, int]], distances: list[int]) -> tuple[Path, Path]:
    """The octile map and version-1 scenario of ``free`` ((rows, cols) bool) and ``agents``
    ((start cell, goal cell), cell = row * cols + col)."""
    rows, cols = free.shape
    m = d / "instance.map"
    m.write_text(f"type octile\nheight {rows}\nwidth {cols}\nmap\n"
                 + "".join("".join("." if f else "@" for f in row) + "\n" for row in free))
    s = d / "instance.scen"
    lines = ["version 1"]
    for (a, b), dist in zip(agents, distances, strict=True):
        lines.append(f"0\tinstance.map\t{cols}\t{rows}\t{a % cols}\t{a // cols}\t{b % cols}\t{b // cols}\t{dist}")
    s.write_text("\n".join(lines) + "\n")
    return m, s


def run_lacam3(binary: Path, free, agents: list[tuple[int, int]], distances: list[int],
               time_limit_s: float) -> dict:
    """Run lacam3's default configuration on one instance; returns its numbers.

    binary: lacam3's ``main``; free: (rows, cols) bool; agents: (start cell, goal cell) per
    agent; distances: each agent's shortest distance (steps, written into the scenario);
    time_limit_s: rounded up to whole seconds (lacam3 takes an integer). Returns
    ``{"solved", "sum_of_costs", "sum_of_loss", "lower_bound", "makespan", "first_solution_s",
    "first_sum_of_loss", "time_s"}`` (``time_s``: the process's wall time, which includes the
    checks lacam3 runs after its clock stops). Raises FileNotFoundError when ``binary`` is
    missing and RuntimeError when lacam3 fails or writes no result.
    """
    binary = Path(binary)
    if not binary.is_file():
        raise FileNotFoundError(f"lacam3 binary not found: {binary}")
    with tempfile.TemporaryDirectory(prefix="lacam3-") as tmp:
        d = Path(tmp)
        m, s = _write_instance(d, free, agents, distances)
        out = d / "result.txt"
        cmd = [str(binary), "-m", str(m), "-i", str(s), "-N", str(len(agents)),
               "-t", str(max(1, math.ceil(time_limit_s))), "-v", "0", "-o", str(out)]
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=10 * time_limit_s + 60)
        wall = time.perf_counter() - t0
        if p.returncode != 0 or not out.is_file():
            raise RuntimeError(f"lacam3 exited {p.returncode}: {(p.stderr or p.stdout).strip()[-300:]}")
        kv = {}
        for ln in out.read_text().splitlines():
            key, sep, val = ln.partition("=")
            if sep and key in ("solved", "soc", "soc_lb", "sum_of_loss", "makespan", "comp_time_initial_solution",
                               "cost_initial_solution"):
                kv[key] = int(val)
    solved = kv.get("solved", 0) == 1 and kv.get("soc", 0) > 0
    first_ms = kv.get("comp_time_initial_solution", -1)
    return {"solved": solved, "sum_of_costs": kv.get("soc") if solved else None,
            "sum_of_loss": kv.get("sum_of_loss") if solved else None, "lower_bound": kv.get("soc_lb"),
            "makespan": kv.get("makespan") if solved else None,
            "first_solution_s": first_ms / 1e3 if first_ms >= 0 else None,
            "first_sum_of_loss": kv.get("cost_initial_solution") if first_ms >= 0 else None, "time_s": wall}
