"""rce_fleet.operations: how the live fleet is run by its operators: tasks, dispatch, places and
batteries, and the task API with its clients.

- :mod:`.places`: named places of a warehouse (stations, chargers, parking), sans-I/O.
- :mod:`.battery`: the robots' batteries, sans-I/O.
- :mod:`.tasks_api`: the task API's requests and answers, sans-I/O.
- :mod:`.dispatcher`: who does what next (tasks, charging, parking), sans-I/O.
- :mod:`.tasks_client`: an RCE client's channel to the fleet's tasks.
- :mod:`.api_models`: the HTTP API's request and response models and its OpenAPI document, sans-I/O.
- :mod:`.api_auth`: who may call the HTTP API: roles, bearer tokens, credentials, sans-I/O.
- :mod:`.http_api`: the JSON HTTP API (authenticated) and Prometheus metrics on the fleet's web server.
- :mod:`.task_cli`: ``rce-fleet task add|list|get|cancel``.

May import :mod:`rce_fleet.maps`, :mod:`rce_fleet.lifelong`, :mod:`rce_fleet.configs` and the engine's
client side; never :mod:`rce_fleet.nodes` or :mod:`rce_fleet.live`. The sans-I/O modules import no
sockets, asyncio or network library.
"""
