"""Named places of a warehouse: pick-up and drop-off stations, chargers and parking spots,
declared in a small YAML file beside the map (``--places FILE``)::

    # places of warehouse.yaml (cells of the grid the fleet runs on, or x/y in metres)
    places:
      - {name: pick1, kind: pickup, cell: 57}
      - {name: drop1, kind: dropoff, x: 12.5, y: -3.0}
      - {name: charger1, kind: charger, cell: 3}
      - {name: park1, kind: parking, cell: 30}

A place given by ``x``/``y`` (map frame, m) is the grid cell that point lies in. Every
place is a free cell of the grid, names are unique and two places never share a cell.
:func:`generate_places` makes such a file for a map that has none (the demo does).

Tasks name places in their errands (``"pick1"``) or give cell numbers (``"57"``):
:meth:`Places.resolve` turns either into a cell, with a :class:`PlaceError` that says why not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from rce.protocol.limits import short_repr

from ..maps.geometry import GridGeometry, components

__all__ = ["KINDS", "PLACES_PARAM", "Place", "PlaceError", "Places", "generate_places"]

KINDS = ("pickup", "dropoff", "charger", "parking")
PAIR_STEPS = 3                   # steps from a pick-up to its drop-off in generate_places(paired=True)
PLACES_PARAM = "/fleet/places"   # the parameter the fleet manager sets for the global planner


class PlaceError(ValueError):
    """A bad places file, or an errand that names no place or cell of the grid."""


@dataclass(frozen=True)
class Place:
    """One place: ``name``, ``kind`` (one of :data:`KINDS`) and its grid ``cell``."""

    name: str
    kind: str
    cell: int


class Places:
    """The places of one grid, by name (see the module docstring). Raises PlaceError for an
    unknown kind, a duplicate name or cell, or a cell that is not a free cell of ``geo``."""

    def __init__(self, places: list[Place], geo: GridGeometry):
        self.geo = geo
        self.by_name: dict[str, Place] = {}
        cells: dict[int, str] = {}
        for p in places:
            if p.kind not in KINDS:
                raise PlaceError(f"place {p.name!r}: unknown kind {p.kind!r} (one of {', '.join(KINDS)})")
            if not p.name or p.name.strip() != p.name or p.name.lstrip("-").isdigit():
                raise PlaceError(f"place name {p.name!r}: a name must be non-empty, untrimmed text, not a number")
            if p.name in self.by_name:
                raise PlaceError(f"place {p.name!r} is declared twice")
            if not geo.is_free(p.cell):
                raise PlaceError(f"place {p.name!r}: cell {p.cell} is not a free cell of the "
                                 f"{geo.rows}x{geo.cols} grid")
            if p.cell in cells:
                raise PlaceError(f"places {cells[p.cell]!r} and {p.name!r} share cell {p.cell}")
            cells[p.cell] = p.name
            self.by_name[p.name] = p
        self.by_cell = {c: self.by_name[n] for c, n in cells.items()}

    def __len__(self) -> int:
        return len(self.by_name)

    def of_kind(self, kind: str) -> list[Place]:
        """The places of ``kind``, in declaration order."""
        return [p for p in self.by_name.values() if p.kind == kind]

    def cells(self, kind: str) -> list[int]:
        """The cells of the places of ``kind``."""
        return [p.cell for p in self.of_kind(kind)]

    def resolve(self, errand: str | int) -> int:
        """The cell of an errand: a place name, or a cell number (int or decimal text) on the
        grid. Raises PlaceError naming the errand (an unknown place lists the known ones)."""
        if isinstance(errand, bool):
            raise PlaceError(f"errand {errand!r}: expected a cell number or a place name")
        if isinstance(errand, int):
            cell = errand
        else:
            text = str(errand).strip()
            if text in self.by_name:
                return self.by_name[text].cell
            try:
                cell = int(text)
            except ValueError:
                known = ", ".join(sorted(self.by_name)) or "none declared"
                raise PlaceError(f"unknown place {short_repr(text)} (places: {known})") from None
        if not self.geo.valid(cell):
            raise PlaceError(f"cell {cell} is outside the {self.geo.rows}x{self.geo.cols} grid "
                             f"(cells 0..{self.geo.n_cells - 1})")
        if not self.geo.is_free(cell):
            raise PlaceError(f"cell {cell} is not a free cell of the grid (a wall or shelf)")
        return cell

    # -- files and the parameter ---------------------------------------------------------------
    def to_param(self) -> list[dict]:
        """JSON form: ``[{"name", "kind", "cell"}, ...]`` (the ``/fleet/places`` parameter)."""
        return [{"name": p.name, "kind": p.kind, "cell": p.cell} for p in self.by_name.values()]

    @classmethod
    def from_param(cls, items: list[dict] | None, geo: GridGeometry) -> Places:
        """Places from :meth:`to_param`'s form (None or empty: no places)."""
        return cls._parse(items or [], geo, "the places parameter")

    @classmethod
    def load(cls, path: str | Path, geo: GridGeometry) -> Places:
        """Read a places YAML (module docstring); raises PlaceError naming the file."""
        try:
            doc = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError) as e:
            raise PlaceError(f"{path}: {e}") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("places"), list):
            raise PlaceError(f"{path}: expected a mapping with a 'places' list")
        return cls._parse(doc["places"], geo, str(path))

    @classmethod
    def _parse(cls, items: list, geo: GridGeometry, where: str) -> Places:
        out = []
        for i, it in enumerate(items):
            if not isinstance(it, dict) or "name" not in it or "kind" not in it:
                raise PlaceError(f"{where}: place {i + 1} needs a name and a kind")
            name, kind = str(it["name"]), str(it["kind"])
            if "cell" in it:
                try:
                    cell = int(it["cell"])
                except (TypeError, ValueError):
                    raise PlaceError(f"{where}: place {name!r}: cell {it['cell']!r} is not a number") from None
            elif "x" in it and "y" in it:
                c = geo.cell_of(float(it["x"]), float(it["y"]))
                if c is None:
                    raise PlaceError(f"{where}: place {name!r}: ({it['x']}, {it['y']}) m is outside the grid")
                cell = c
            else:
                raise PlaceError(f"{where}: place {name!r} needs a cell or x and y")
            out.append(Place(name, kind, cell))
        try:
            return cls(out, geo)
        except PlaceError as e:
            raise PlaceError(f"{where}: {e}") from None

    def dump(self, path: str | Path, note: str = "") -> Path:
        """Write the places YAML to ``path``; returns it."""
        p = Path(path)
        lines = [f"# {note}" if note else "# places of the fleet's grid (rce-fleet --places)", "places:"]
        lines += [f"  - {{name: {q.name}, kind: {q.kind}, cell: {q.cell}}}" for q in self.by_name.values()]
        p.write_text("\n".join(lines) + "\n")
        return p


def generate_places(geo: GridGeometry, robots: int, stations: int | None = None, paired: bool = False) -> Places:
    """Places for a map without a file, in the largest connected part of the grid: pick-up
    stations in the left third, drop-off stations in the right third (``stations`` each;
    default one per four robots, at least 2 and up to 6, and at most one per 40 cells; ``paired``:
    the pick-ups spread over the whole part instead, each with a drop-off :data:`PAIR_STEPS` steps
    from it, as a workstation's in and out),
    ``ceil(robots / 3)`` chargers spread over the top rows, and parking on dead ends
    and cells along walls, towards the map's edges, as many as there
    are robots where the grid has them. A robot may stand on any place for long, so no place
    cuts the free cells apart: every place leaves the rest of the part connected and keeps a
    free neighbour. Raises PlaceError when the grid is too small."""
    parts = components(geo)
    comp = sorted(parts[0]) if parts else []
    n_st = stations or max(2, min(max(6, robots // 4), len(comp) // 40))
    n_ch = max(1, math.ceil(robots / 3))
    if len(comp) < 2 * n_st + n_ch + 2:
        raise PlaceError(f"the grid's largest connected part has {len(comp)} cells: too few for places")
    inside = set(comp)
    nbrs = {c: [n for n in geo.neighbours(c) if n in inside] for c in comp}
    deg = {c: len(v) for c, v in nbrs.items()}
    cols = [geo.rc(c)[1] for c in comp]
    lo, hi = min(cols), max(cols)
    span = max(1, hi - lo)
    taken: set[int] = set()

    def safe(c: int) -> bool:
        """Whether a robot standing on ``c`` (and on every place so far) leaves the rest connected."""
        gone = taken | {c}
        if not any(n not in gone for n in nbrs[c]):
            return False
        start = next(x for x in comp if x not in gone)
        seen, todo = {start}, [start]
        while todo:
            for n in nbrs[todo.pop()]:
                if n not in gone and n not in seen:
                    seen.add(n)
                    todo.append(n)
        return len(seen) == len(comp) - len(gone)

    def dist(a: int, b: int) -> int:
        (ra, ca), (rb, cb) = geo.rc(a), geo.rc(b)
        return abs(ra - rb) + abs(ca - cb)

    def spread(cands: list[int], k: int) -> list[int]:
        """Up to k safe cells of ``cands`` far apart (farthest-point sampling from the first)."""
        pick: list[int] = []
        cands = [c for c in cands if c not in taken]
        while len(pick) < k and cands:
            best = cands[0] if not pick else max(cands, key=lambda c: min(dist(c, p) for p in pick))
            cands.remove(best)
            if safe(best):
                pick.append(best)
                taken.add(best)
        return pick

    top = sorted(comp, key=lambda c: (geo.rc(c)[0], geo.rc(c)[1]))
    places = [Place(f"charger{i + 1}", "charger", c) for i, c in enumerate(spread(top[:max(n_ch * 6, 12)], n_ch))]
    # stations below the chargers' rows
    low = max(geo.rc(p.cell)[0] for p in places) + 2
    if sum(1 for c in comp if geo.rc(c)[0] >= low) < 4 * n_st:
        low = 0
    left = [c for c in comp if geo.rc(c)[1] - lo <= span / 3 and deg[c] >= 2 and geo.rc(c)[0] >= low]
    right = [c for c in comp if hi - geo.rc(c)[1] <= span / 3 and deg[c] >= 2 and geo.rc(c)[0] >= low]
    if paired:
        room = {c for c in comp if deg[c] >= 2 and geo.rc(c)[0] >= low}      # off the chargers' rows
        pairs = [(p, _pair(p, nbrs, room, safe, taken)) for p in spread(sorted(room), n_st)]
        picks, drops = [p for p, d in pairs if d is not None], [d for _, d in pairs if d is not None]
    else:
        picks, drops = spread(left, n_st), spread(right, n_st)
    places += [Place(f"pick{i + 1}", "pickup", c) for i, c in enumerate(picks)]
    places += [Place(f"drop{i + 1}", "dropoff", c) for i, c in enumerate(drops)]
    # parking: dead ends first, then cells along walls (degree 3), then corridors, far from
    # the middle and from the stations
    mid_r = sum(geo.rc(c)[0] for c in comp) / len(comp)
    mid_c = sum(geo.rc(c)[1] for c in comp) / len(comp)
    stations = [p.cell for p in places]
    order = sorted((c for c in comp if c not in taken and deg[c] < 4),
                   key=lambda c: ({1: 0, 3: 1, 2: 2}.get(deg[c], 3), min(dist(c, x) for x in stations) < 3,
                                  -abs(geo.rc(c)[0] - mid_r) - abs(geo.rc(c)[1] - mid_c)))
    parking = []
    for c in order:
        if len(parking) >= robots:
            break
        if all(dist(c, x) > 1 for x in parking) and safe(c):
            parking.append(c)
            taken.add(c)
    places += [Place(f"park{i + 1}", "parking", c) for i, c in enumerate(parking)]
    return Places(places, geo)


def _pair(pick: int, nbrs: dict[int, list[int]], room: set[int], safe, taken: set[int]) -> int | None:
    """A drop-off for ``pick``: the first cell (by number) of ``room`` :data:`PAIR_STEPS` steps from it that
    ``safe`` allows (taken then), nearer ones if none; None when there is none."""
    seen, ring = {pick}, [pick]
    rings = []
    for _ in range(PAIR_STEPS):
        ring = sorted({n for c in ring for n in nbrs[c] if n not in seen})
        seen.update(ring)
        rings.append(ring)
    for ring in reversed(rings):
        for c in ring:
            if c in room and c not in taken and safe(c):
                taken.add(c)
                return c
    return None
