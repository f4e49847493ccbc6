"""Maps no planner constant was set on: the held-out set of ``bench/lifelong.py --heldout``.

The lifelong planner chooses some of its methods by constants measured on the League's maps and on
maps of the project's own (docs/results/lifelong.md). A constant that only fits the maps it was set
on shows on maps it never saw. This module makes such maps from a seed, with code that shares
nothing with the planner (it imports nothing of ``rce_fleet``), in four families whose shapes the
tuned set does not have in these sizes:

- ``maze``: a maze of corridors ``w`` cells wide (a depth-first labyrinth, every corridor a dead end
  or a junction), with ``loops`` extra openings in its walls.
- ``rooms``: a grid of ``room`` x ``room`` rooms, each wall between two rooms with one door of
  ``door`` cells at a random place, and a few pillars inside the rooms.
- ``shelves``: a warehouse of shelf blocks ``bh`` x ``bw`` in aisles ``aisle`` cells wide, framed by
  an open working area ``margin`` cells deep on two sides.
- ``caves``: a cellular automaton's caves (random fill, smoothed by the 4-5 rule), the largest
  connected cave kept.

Maps are MovingAI octile files (``.`` free, ``@`` blocked), the format the League's start-kit reads.
The set is fixed by its seeds (:data:`HELDOUT`): the same files on every machine.
"""
from __future__ import annotations

import random
from collections import deque
from pathlib import Path

# name -> (family, parameters, seed): the held-out set
HELDOUT = {
    "maze-49-49-w1": ("maze", {"size": 49, "w": 1, "loops": 40}, 11),
    "rooms-60-60-r9-d1": ("rooms", {"size": 60, "room": 9, "door": 1}, 13),
    "shelves-72-48-b2x6": ("shelves", {"rows": 48, "cols": 72, "bh": 2, "bw": 6, "aisle": 1, "margin": 4}, 15),
    "caves-64-64": ("caves", {"size": 64, "fill": 0.45}, 17),
}
# the same families at sizes that hold teams over 1,000 at 0.1 robots per free cell, where the planner's
# thresholds choose between its step planners (19,408 - 27,807 free cells)
HELDOUT_LARGE = {
    "shelves-240-160-b2x8": ("shelves", {"rows": 160, "cols": 240, "bh": 2, "bw": 8, "aisle": 1, "margin": 8}, 21),
    "caves-200-200": ("caves", {"size": 200, "fill": 0.45}, 23),
    "rooms-180-180-r11-d2": ("rooms", {"size": 180, "room": 11, "door": 2}, 25),
}
EVERY = {**HELDOUT, **HELDOUT_LARGE}    # every held-out map by name


def _maze(rnd: random.Random, size: int, w: int, loops: int) -> list[list[bool]]:
    step = w + 1
    n = (size - 1) // step
    free = [[False] * size for _ in range(size)]

    def carve(r0: int, c0: int, r1: int, c1: int) -> None:
        for r in range(min(r0, r1), max(r0, r1) + w):
            for c in range(min(c0, c1), max(c0, c1) + w):
                free[r][c] = True

    seen = {(0, 0)}
    stack = [(0, 0)]
    carve(1, 1, 1, 1)
    while stack:
        i, j = stack[-1]
        nxt = [(i + di, j + dj) for di, dj in ((0, 1), (1, 0), (0, -1), (-1, 0))
               if 0 <= i + di < n and 0 <= j + dj < n and (i + di, j + dj) not in seen]
        if not nxt:
            stack.pop()
            continue
        a, b = rnd.choice(nxt)
        carve(1 + i * step, 1 + j * step, 1 + a * step, 1 + b * step)
        seen.add((a, b))
        stack.append((a, b))
    for _ in range(loops):                       # openings in walls between two corridors
        r, c = rnd.randrange(1, size - 1), rnd.randrange(1, size - 1)
        if not free[r][c] and ((free[r - 1][c] and free[r + 1][c]) or (free[r][c - 1] and free[r][c + 1])):
            free[r][c] = True
    return free


def _rooms(rnd: random.Random, size: int, room: int, door: int) -> list[list[bool]]:
    free = [[True] * size for _ in range(size)]
    walls = list(range(room, size, room + 1))
    for x in walls:
        for k in range(size):
            free[x][k] = free[k][x] = False
    bounds = [-1, *walls, size]
    for bi in range(len(bounds) - 1):
        lo, hi = bounds[bi] + 1, bounds[bi + 1]           # a room's span on one axis
        if hi - lo < door:
            continue
        for x in walls:                                    # one door in each wall piece of this span
            start = rnd.randrange(lo, hi - door + 1)
            for k in range(start, start + door):
                free[x][k] = True
                free[k][x] = True
    for _ in range(size * size // 60):                     # pillars, never on a door's line
        r, c = rnd.randrange(size), rnd.randrange(size)
        if free[r][c] and all(0 < r + dr < size - 1 and 0 < c + dc < size - 1 and free[r + dr][c + dc]
                              for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))):
            free[r][c] = False
    return free


def _shelves(rnd: random.Random, rows: int, cols: int, bh: int, bw: int, aisle: int, margin: int) -> list[list[bool]]:
    free = [[True] * cols for _ in range(rows)]
    r = margin
    while r + bh <= rows - aisle:
        c = margin
        while c + bw <= cols - aisle:
            if rnd.random() > 0.06:                       # now and then a block is missing: a cross-aisle
                for dr in range(bh):
                    for dc in range(bw):
                        free[r + dr][c + dc] = False
            c += bw + aisle
        r += bh + aisle
    return free


def _caves(rnd: random.Random, rows: int, cols: int, fill: float) -> list[list[bool]]:
    wall = [[rnd.random() < fill for _ in range(cols)] for _ in range(rows)]
    for _ in range(5):
        nxt = [[False] * cols for _ in range(rows)]
        for r in range(rows):
            for c in range(cols):
                k = sum(1 for dr in (-1, 0, 1) for dc in (-1, 0, 1)
                        if (dr or dc) and not (0 <= r + dr < rows and 0 <= c + dc < cols and not wall[r + dr][c + dc]))
                nxt[r][c] = k >= 5 or (wall[r][c] and k >= 4)
        wall = nxt
    return [[not w for w in row] for row in wall]


def _largest(free: list[list[bool]]) -> list[list[bool]]:
    """``free`` with only its largest 4-connected part left free."""
    rows, cols = len(free), len(free[0])
    label = [[-1] * cols for _ in range(rows)]
    best, best_n = -1, 0
    for r0 in range(rows):
        for c0 in range(cols):
            if not free[r0][c0] or label[r0][c0] >= 0:
                continue
            k = r0 * cols + c0
            label[r0][c0] = k
            q, n = deque([(r0, c0)]), 0
            while q:
                r, c = q.popleft()
                n += 1
                for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0)):
                    a, b = r + dr, c + dc
                    if 0 <= a < rows and 0 <= b < cols and free[a][b] and label[a][b] < 0:
                        label[a][b] = k
                        q.append((a, b))
            if n > best_n:
                best, best_n = k, n
    return [[label[r][c] == best for c in range(cols)] for r in range(rows)]


def make_map(name: str) -> list[list[bool]]:
    """The held-out map ``name`` (a key of :data:`HELDOUT` or :data:`HELDOUT_LARGE`) as rows of free
    (True) cells, its largest connected part only. Raises KeyError for a name not in the set."""
    family, kw, seed = EVERY[name]
    rnd = random.Random(seed)
    if family == "maze":
        free = _maze(rnd, **kw)
    elif family == "rooms":
        free = _rooms(rnd, **kw)
    elif family == "shelves":
        free = _shelves(rnd, **kw)
    else:
        kw = {"rows": kw.get("rows", kw.get("size")), "cols": kw.get("cols", kw.get("size")), "fill": kw["fill"]}
        free = _caves(rnd, **kw)
    return _largest(free)


def write_maps(folder: Path, names: list[str] | None = None) -> dict[str, tuple[Path, int]]:
    """Write the held-out maps (all of :data:`HELDOUT`, or ``names``) to ``folder`` as ``NAME.map``.
    Returns name -> (path, free cells)."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name in names or HELDOUT:
        free = make_map(name)
        rows, cols = len(free), len(free[0])
        body = "\n".join("".join("." if x else "@" for x in row) for row in free)
        path = folder / f"{name}.map"
        path.write_text(f"type octile\nheight {rows}\nwidth {cols}\nmap\n{body}\n")
        out[name] = (path, sum(map(sum, free)))
    return out


if __name__ == "__main__":
    import sys
    for n, (p, cells) in write_maps(Path(sys.argv[1] if len(sys.argv) > 1 else "heldout")).items():
        print(f"{n}: {p} ({cells} free cells)")
