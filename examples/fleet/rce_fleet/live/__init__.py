"""rce_fleet.live: the fleet running on one machine: the demo run and its output, the simulator host,
the operator's web page, injected faults, simulated radios and the bag recorder.

- :mod:`.demo`: ``rce-fleet demo`` / ``rce-fleet serve``: the whole fleet system.
- :mod:`.options`: their flags, parsed and checked before the run's imports (a bad flag is refused at once).
- :mod:`.task_stream`: the generated task stream of a lifelong run and its report sections.
- :mod:`.demo_output`: the live table, progress line, ``--report`` JSON and PNGs.
- :mod:`.plot`: PNG of a run's map and robot paths.
- :mod:`.kinematic`: the control loop without physics and without the engine.
- :mod:`.simhost`: the simulator host (one :class:`rce_fleet.sim.SimWorld`, a bridge per robot).
- :mod:`.points_wire`: the simulated robots' obstacle messages, packed.
- :mod:`.manager`: the fleet manager, the cloud side's operator client.
- :mod:`.webui`: the operator's web page (static files in ``web/``).
- :mod:`.faults`, :mod:`.linkproxy`, :mod:`.radio`: faults, links through a proxy, radios.
- :mod:`.fleet_bag`: the fleet's topics recorded into a ROS 1 bag or an MCAP file.
- :mod:`.fleet_scene`, :mod:`.foxglove`: the live fleet for Foxglove and Lichtblick (map, poses, paths,
  markers) over the Foxglove WebSocket protocol.
- :mod:`.replay`: ``rce-fleet replay``: a recording played back onto the operator page.

The top layer below :mod:`rce_fleet.cli`: may import every other part of rce_fleet; nothing but the
CLI imports it.
"""
