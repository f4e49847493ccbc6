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

The relay floor (``relay_port``): the engine's topology with nothing else in it. Each floor
process sends every pose frame, with the robot's number, over one TCP link to an echo process
(:func:`echo_main`, standing for the node: it writes back every byte it reads) and writes what
comes back to the robot's websocket: the hops robot -> rce-robot -> node -> rce-robot -> robot,
each pose crossing a process twice more than on the plain floor. Link frames are
``<u32 length><u32 robot><u8 kind>`` then the payload (kind 0: a text frame, 1: a binary part).
"""
from __future__ import annotations

import asyncio
import json
import socket
import struct
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

from fleet_wiring import echo_tags
from rce_robot import ws_cork


LINK_HEADER = struct.Struct("<IIB")      # payload length (bytes), robot number, kind (0 text, 1 binary)


class _Echo(asyncio.Protocol):
    """The relay floor's node: every byte read is written back."""

    def connection_made(self, transport) -> None:
        self.transport = transport
        transport.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def data_received(self, data: bytes) -> None:
        self.transport.write(data)


class _RelayLink(asyncio.Protocol):
    """A floor process's link to the echo: frames back from it go to their robot's websocket."""

    def __init__(self, robots: dict):
        self.robots, self.buf = robots, bytearray()

    def connection_made(self, transport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.buf += data
        off, n = 0, len(self.buf)
        while n - off >= LINK_HEADER.size:
            size, robot, kind = LINK_HEADER.unpack_from(self.buf, off)
            end = off + LINK_HEADER.size + size
            if end > n:
                break
            payload = bytes(self.buf[off + LINK_HEADER.size:end])
            ws = self.robots.get(robot)
            if ws is not None and ws_cork.writable(ws):
                ws_cork.write(ws, (payload if kind else payload.decode(),))
            off = end
        del self.buf[:off]

    def send(self, robot: int, frame: str | bytes) -> None:
        kind = isinstance(frame, bytes)
        data = frame if kind else frame.encode()
        self.transport.writelines((LINK_HEADER.pack(len(data), robot, kind), data))


async def serve_floor(sock: socket.socket, side: str, ready=None, relay_port: int | None = None) -> None:
    """Serve the floor on the bound, listening ``sock`` until cancelled; ``ready()`` once it is up.
    With ``relay_port``, poses go through the echo process listening there (the relay floor)."""
    from websockets.asyncio.server import serve
    from websockets.datastructures import Headers
    from websockets.exceptions import ConnectionClosed
    from websockets.http11 import Response

    host, port = sock.getsockname()[:2]
    answer = json.dumps({"url": f"ws://{host}:{port}/"}).encode()
    robots: dict = {}
    link = None
    if relay_port is not None:
        _, link = await asyncio.get_running_loop().create_connection(lambda: _RelayLink(robots), "127.0.0.1",
                                                                     relay_port)
        link.transport.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

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
        robots[n] = ws
        try:
            async for frame in ws:
                if not ws_cork.writable(ws):
                    await ws.drain()                         # the robot does not read: wait for it
                if isinstance(frame, bytes):
                    if link is not None:
                        link.send(n, frame)
                    else:
                        ws_cork.write(ws, (frame,))
                elif pose_key in frame:
                    if link is not None:
                        link.send(n, frame.replace(pose_key, echo_key, 1))
                    else:
                        ws_cork.write(ws, (frame.replace(pose_key, echo_key, 1),))
                elif (m := json.loads(frame)).get("type") == "CN":      # set-up only: parsed
                    ws_cork.write(ws, [json.dumps({"type": "ST", "data": {"topic": "iu", "iTag": a["interfaceTag"],
                                                                          "status": True}})
                                       for a in m["data"].get("addInterfaces", []) if a.get("endpointTag") == rid])
        except ConnectionClosed:       # the robot went away (the run is over)
            pass
        finally:
            if robots.get(n) is ws:
                del robots[n]

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


def floor_main(port: int, side: str, conn, relay_port: int | None = None) -> None:
    """Entry point of one floor process: serve on ``port`` (shared), say ``ready`` on ``conn``;
    with ``relay_port``, relay every pose through the echo process there."""
    from rce.plumbing.process import run_loop
    sock = floor_socket(port=port)
    try:
        run_loop(serve_floor(sock, side, ready=lambda: conn.send("ready"), relay_port=relay_port))
    except KeyboardInterrupt:
        pass


def echo_main(conn) -> None:
    """Entry point of the relay floor's echo process: listen on an ephemeral loopback port, send
    the port on ``conn``, write back every byte each connection sends."""
    from rce.plumbing.process import run_loop

    async def serve() -> None:
        srv = await asyncio.get_running_loop().create_server(_Echo, "127.0.0.1", 0)
        conn.send(srv.sockets[0].getsockname()[1])
        await asyncio.Future()
    try:
        run_loop(serve())
    except KeyboardInterrupt:
        pass
