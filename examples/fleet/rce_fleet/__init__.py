"""The warehouse fleet of the seed paper on rce: maps and the cell grid, the multi-robot
planner (:mod:`rce_fleet.planning`), the global planner and move_client container nodes, a
simulator, the operator's web page and ``rce-fleet`` (see ``examples/fleet/README.md``)."""
