"""The warehouse fleet of the seed paper on rce, by part (``docs/layout.md``):

- :mod:`rce_fleet.maps`: maps, the cell grid and its geometry;
- :mod:`rce_fleet.planning`: the one-shot multi-robot planner (prioritised SIPP, LaCAM);
- :mod:`rce_fleet.lifelong`: the lifelong planner, its tasks and the League of Robot Runners rules;
- :mod:`rce_fleet.sim`: the simulated robots' world, sans-I/O;
- :mod:`rce_fleet.operations`: tasks, dispatch, places, batteries and the task API;
- :mod:`rce_fleet.nodes`: the global planner and move_client container nodes;
- :mod:`rce_fleet.live`: the demo run, the simulator host, the operator's page and faults;
- :mod:`rce_fleet.cli`: ``rce-fleet`` (see ``examples/fleet/README.md``).
"""
