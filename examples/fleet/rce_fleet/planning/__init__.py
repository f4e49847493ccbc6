"""The fleet's multi-robot planner (sans-I/O: plain classes, no sockets, no asyncio).

One module per job:

- :mod:`.graph`: the grid graph (free cells, 4-neighbour moves) and its distances.
- :mod:`.movingai`: MovingAI benchmark maps and scenarios (Sturtevant 2012).
- :mod:`.dijkstra`: single-robot shortest paths (the seed paper's planner) and the
  true-distance heuristic table (Dijkstra 1959).
- :mod:`.paths`: space-time paths and their conflicts (Stern et al. 2019).
- :mod:`.reservations`: the reservation table (Silver 2005).
- :mod:`.sipp`: one robot around the reservations, safe interval path planning
  (Phillips & Likhachev 2011); its search compiled in :mod:`.sipp_kernel` (numba).
- :mod:`.prioritized`: one (re)plan of many robots, prioritized planning with priority
  bumping (Erdmann & Lozano-Perez 1987; Silver 2005).
- :mod:`.adg`: execution in plan order under delays, the action dependency graph
  (Hoenig et al. 2019).
- :mod:`.fleet_planner`: :class:`FleetPlanner`, the state of the fleet (positions, goals,
  blocked cells, paths) and its re-planning; the global planner node's core
  (:mod:`rce_fleet.nodes.global_planner_core`) is a thin layer around it.

Units: cells are integers ``r * cols + c`` (row 0 at the top of the map image, see
:mod:`rce_fleet.maps.grid`); steps are plan time steps (one cell move or one wait).
"""
from .adg import ActionDependencyGraph
from .dijkstra import DistanceTable, shortest_path
from .fleet_planner import FleetPlanner, PlannerError, PlanResult, UnreachableGoal
from .graph import GridGraph
from .movingai import load_movingai_map, load_movingai_scen
from .paths import Conflict, check_conflicts, compress, compressed_index
from .prioritized import SearchLimits
from .reservations import Reservations
from .sipp import safe_interval_astar

__all__ = [
    "ActionDependencyGraph", "Conflict", "DistanceTable", "FleetPlanner", "GridGraph", "PlanResult", "PlannerError",
    "Reservations", "SearchLimits", "UnreachableGoal", "check_conflicts", "compress", "compressed_index",
    "load_movingai_map", "load_movingai_scen", "safe_interval_astar", "shortest_path",
]
