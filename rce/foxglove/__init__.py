"""The Foxglove WebSocket protocol (``foxglove.websocket.v1``), so that Foxglove and Lichtblick show what
rce carries: :mod:`rce.foxglove.protocol` (sans I/O: one client's state, typed events, the server's
messages) and :mod:`rce.foxglove.server` (:class:`~rce.foxglove.server.FoxgloveServer`, the asyncio shell
on ``websockets``, with a login hook, bounded per-client queues and ``/metrics``).

Imports the layers below it (``rce.plumbing``, ``rce.protocol``); imported by ``rce_robot`` and the fleet's
live part.
"""
