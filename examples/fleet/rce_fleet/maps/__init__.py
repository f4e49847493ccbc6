"""rce_fleet.maps: the warehouse as a map: ROS map_server occupancy grids, the project's own lab map,
the global planner's grid of cells and the geometry between cells and metres (sans-I/O but for
reading and writing map files).

- :mod:`.occupancy`: map_server maps (PGM/PNG + YAML) as numpy occupancy grids.
- :mod:`.lab_map`: the project's default map, generated.
- :mod:`.grid`: an occupancy map cut into the planner's grid of cells.
- :mod:`.geometry`: cell numbers <-> world metres, free cells and their components.

The bottom layer: imports nothing else of rce_fleet, and no sockets.
"""
