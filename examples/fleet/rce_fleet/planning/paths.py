"""Space-time paths and the conflicts between them.

A path is a sequence of cells, one per plan step (a move to a neighbour or a wait, which
repeats the cell); after its last step a robot stays in its final cell for ever. A set of
paths is valid when no two robots occupy one cell at one step (vertex conflict), no two
swap cells between two steps (swapping conflict) and no three or more move round a cycle,
each into the cell the next one leaves (cycle conflict). The names are those of Stern et
al. 2019, "Multi-Agent Pathfinding: Definitions, Variants, and Benchmarks" (SoCS); the
cycle rule is there because ordered execution (:mod:`.adg`) cannot carry a rotation out.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

__all__ = ["Conflict", "check_conflicts", "compress", "compressed_index"]


def compress(path: Iterable[int]) -> list[int]:
    """Drop repeated consecutive cells (waits) from a space-time path; cells as ``int``."""
    out: list[int] = []
    for c in path:
        c = int(c)
        if not out or out[-1] != c:
            out.append(c)
    return out


def compressed_index(path: Sequence[int], step: int) -> int:
    """Index in ``compress(path)`` of the cell at ``step`` of ``path``."""
    n = 0
    for i in range(1, min(step, len(path) - 1) + 1):
        if path[i] != path[i - 1]:
            n += 1
    return n


@dataclass(frozen=True)
class Conflict:
    """Two robots in one cell at one step (``kind='vertex'``, ``cells=(c,)``);
    swapping cells between ``step`` and ``step + 1`` (``kind='swap'``, ``cells=(a, b)``:
    ``robots[0]`` goes a -> b, ``robots[1]`` b -> a); or a rotation (``kind='cycle'``):
    three or more robots each entering, between ``step`` and ``step + 1``, the cell
    the next one leaves (``cells``: where each robot starts the move)."""

    kind: str
    robots: tuple[str, ...]
    cells: tuple[int, ...]
    step: int


def check_conflicts(paths: Mapping[str, Sequence[int]], ignore_start: bool = False) -> list[Conflict]:
    """All vertex, swap and rotation conflicts in a set of space-time paths.

    ``paths[robot][k]`` is the robot's cell at step k; after its last step a
    robot stays in its final cell for ever (so a robot passing through another's
    final cell later is a conflict). Empty paths are ignored. With
    ``ignore_start`` shared cells at step 0 are not reported (robots that were
    localised into one cell). Two robots that stay in one cell for ever are
    reported once. Cost O(robots x makespan).
    """
    items = [(r, list(p)) for r, p in paths.items() if len(p)]
    if not items:
        return []
    horizon = max(len(p) for _, p in items)
    out: list[Conflict] = []
    prev: dict[int, str] = {}
    lengths = dict((r, len(p)) for r, p in items)
    for t in range(horizon):
        at: dict[int, str] = {}
        for r, p in items:
            c = p[t] if t < len(p) else p[-1]
            other = at.get(c)
            if other is not None:
                static = t > lengths[r] - 1 and t > lengths[other] - 1   # both parked since before t
                if not (ignore_start and t == 0) and not static:
                    out.append(Conflict("vertex", (other, r), (c,), t))
            else:
                at[c] = r
        if t > 0:
            for r, p in items:
                if t >= len(p):
                    continue
                a, b = p[t - 1], p[t]
                if a == b:
                    continue
                o = prev.get(b)   # who was in b at t-1 ...
                if o is not None and o != r and at.get(a) == o:   # ... and is in a at t
                    if r < o:   # report each swap once
                        out.append(Conflict("swap", (r, o), (a, b), t - 1))
            out.extend(_rotations(items, prev, t))
        prev = at
    return out



def _rotations(items: list[tuple[str, list[int]]], prev: dict[int, str], step: int) -> list[Conflict]:
    """Cycles of >= 3 robots each moving into the cell the next one leaves, between t-1 and t.

    A plan may not contain them: executed with :class:`.adg.ActionDependencyGraph`
    (enter a cell only after its previous occupant has left) they deadlock.
    """
    nxt: dict[str, str] = {}
    move: dict[str, tuple[int, int]] = {}
    for r, p in items:
        if step < len(p) and p[step] != p[step - 1]:
            o = prev.get(p[step])
            move[r] = (p[step - 1], p[step])
            if o is not None and o != r:
                nxt[r] = o
    out, done = [], set()
    for r in nxt:
        if r in done:
            continue
        seen, x = [], r
        while x in nxt and x not in seen and x not in done and x in move:
            seen.append(x)
            x = nxt[x]
        if x in seen and x in move:
            cyc = seen[seen.index(x):]
            if len(cyc) >= 3:
                out.append(Conflict("cycle", tuple(cyc), tuple(move[c][0] for c in cyc), step - 1))
        done.update(seen)
    return out

