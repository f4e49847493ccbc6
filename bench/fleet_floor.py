"""The transport floor of the fleet load (:mod:`fleet_load`): what the same simulated robots get
from a server that does nothing but the websocket hop.

Each floor process serves, on one port shared with ``SO_REUSEPORT`` (one process per robot task
set of the engine, so both use the same cores):

- the login, ``GET /?userID=U&version=V`` -> ``{"url": "ws://HOST:PORT/"}``, as the master
  answers it (no password check: the floor has no users);
- a robot's websocket (``?robotID=RobotN``, the rest of the query is ignored): a ``CN`` is
  answered with ``ST iu`` (up) for each robot-side interface it adds, so the robot's setup
  completes; a ``DM`` on the robot's pose interface comes back unchanged on its echo interface
  (the text frame with the iTag swapped, a binary part as it came); everything else is dropped.

That is one websocket hop each way on the engine's own library and event loop (websockets on
uvloop, corked writes by :mod:`rce_robot.ws_cork`), with no routing, no checks, no container and
no planner: the engine's path takes the same two hops and more. What the floor cannot carry at N
robots on this machine, the engine cannot either.
"""
from __future__ import annotations

import asyncio
import json
import socket
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

from fleet_wiring import echo_tags
from rce_robot import ws_cork


async def serve_floor(sock: socket.socket, side: str, ready=None) -> None:
    """Serve the floor on the bound, listening ``sock`` until cancelled; ``ready()`` once it is up."""
    from websockets.asyncio.server import serve
    from websockets.datastructures import Headers
    from websockets.exceptions import ConnectionClosed
    from websockets.http11 import Response

    host, port = sock.getsockname()[:2]
    answer = json.dumps({"url": f"ws://{host}:{port}/"}).encode()

    def login(conn, request):
        if request.headers.get("Upgrade", "").lower() == "websocket":
            return None                                     # a robot's websocket
        return Response(HTTPStatus.OK, "OK", Headers({"Content-Type": "application/json",
                                                      "Content-Length": str(len(answer))}), answer)

    async def robot(ws) -> None:
        rid = parse_qs(urlsplit(ws.request.path).query).get("robotID", [""])[0]
        n = int(rid[5:]) if rid.startswith("Robot") and rid[5:].isdigit() else 0
        pose, echo = echo_tags(n, side)
        pose_key, echo_key = f'"iTag":"{pose}"', f'"iTag":"{echo}"'
        try:
            async for frame in ws:
                if not ws_cork.writable(ws):
                    await ws.drain()                         # the robot does not read: wait for it
                if isinstance(frame, bytes):
                    ws_cork.write(ws, (frame,))
                elif pose_key in frame:
                    ws_cork.write(ws, (frame.replace(pose_key, echo_key, 1),))
                elif (m := json.loads(frame)).get("type") == "CN":      # set-up only: parsed
                    ws_cork.write(ws, [json.dumps({"type": "ST", "data": {"topic": "iu", "iTag": a["interfaceTag"],
                                                                          "status": True}})
                                       for a in m["data"].get("addInterfaces", []) if a.get("endpointTag") == rid])
        except ConnectionClosed:       # the robot went away (the run is over)
            pass

    async with serve(robot, sock=sock, process_request=login, max_size=None, compression=None,
                     ping_interval=None, max_queue=None):
        if ready is not None:
            ready()
        await asyncio.Future()


def floor_socket(host: str = "127.0.0.1", port: int = 0) -> socket.socket:
    """A listening TCP socket with ``SO_REUSEPORT`` (several floor processes share the port)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    s.bind((host, port))
    s.listen(1024)
    return s


def floor_main(port: int, side: str, conn) -> None:
    """Entry point of one floor process: serve on ``port`` (shared), say ``ready`` on ``conn``."""
    from rce.plumbing.process import run_loop
    sock = floor_socket(port=port)
    try:
        run_loop(serve_floor(sock, side, ready=lambda: conn.send("ready")))
    except KeyboardInterrupt:
        pass
