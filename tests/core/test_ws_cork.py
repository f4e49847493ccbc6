"""rce_robot.ws_cork and the robot namespace's write path, over real websockets on loopback: a
message's frames leave in one corked write, in order; a robot that does not read holds the rest in
the session's bounded outbox (the link pauses), and gets everything, in order, once it reads."""
from __future__ import annotations

import asyncio
import json

from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from rce.protocol.session import RobotSession, SessionLimits
from rce_robot import ws_cork
from rce_robot.namespace import RobotNamespace

STEP = 10.0          # s, the longest any single wait may take
PART = 64 * 1024     # bytes of each forwarded message in the backpressure test
COUNT = 300          # messages: ~19 MB, far more than loopback's socket buffers hold


async def until(cond, what: str) -> None:
    """Poll ``cond()`` until true, at most STEP s."""
    deadline = asyncio.get_running_loop().time() + STEP
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


class Served:
    """A websocket server whose connections are each served by a RobotNamespace (no master)."""

    def __init__(self):
        self.namespaces: list[RobotNamespace] = []

    async def handler(self, ws) -> None:
        async def gone(_ns) -> None:
            return None
        session = RobotSession("robot", SessionLimits(queue_size=COUNT * 2))
        ns = RobotNamespace("u", f"r{len(self.namespaces)}", None, session, on_gone=gone)
        self.namespaces.append(ns)
        await ns.serve(ws)

    async def __aenter__(self):
        self.server = await serve(self.handler, "127.0.0.1", 0, max_size=None, compression=None)
        self.url = f"ws://127.0.0.1:{self.server.sockets[0].getsockname()[1]}/"
        return self

    async def __aexit__(self, *exc):
        self.server.close()
        await self.server.wait_closed()


async def test_write_sends_a_messages_frames_in_order():
    async with Served() as srv, connect(srv.url, max_size=None, compression=None) as client:
        await until(lambda: srv.namespaces and srv.namespaces[0].ws is not None, "the session")
        ws = srv.namespaces[0].ws
        assert ws_cork.corkable(ws) and ws_cork.writable(ws) and not ws_cork.paused(ws)
        n = ws_cork.write(ws, ['{"type":"ST","data":1}', b"x" * 40, b"y" * 200])
        # server frames are unmasked: a 2-byte header, +2 for a payload of 126 bytes or more (RFC 6455 5.2)
        assert n == (2 + 22) + (2 + 40) + (4 + 200)
        assert await asyncio.wait_for(client.recv(), STEP) == '{"type":"ST","data":1}'
        assert await asyncio.wait_for(client.recv(), STEP) == b"x" * 40
        assert await asyncio.wait_for(client.recv(), STEP) == b"y" * 200


async def test_a_robot_that_does_not_read_pauses_the_link_and_gets_everything_in_order():
    async with Served() as srv, connect(srv.url, max_size=None, compression=None, max_queue=1) as client:
        await until(lambda: srv.namespaces and srv.namespaces[0].ws is not None, "the session")
        ns = srv.namespaces[0]
        ns.session.add_interface("cam", "PublisherForwarder", "std_msgs/String")
        for i in range(COUNT):        # control DMs (data=False): never dropped
            assert ns.send_dm("cam", "std_msgs/String", str(i), i.to_bytes(4, "little") + bytes(PART - 4))
        # the client reads nothing: the transport pauses, the rest waits in the session's outbox
        await until(lambda: ws_cork.paused(ns.ws), "the link to pause")
        assert ns.session.outbox > 0 and not ws_cork.writable(ns.ws)
        got = []
        while len(got) < COUNT:
            text = json.loads(await asyncio.wait_for(client.recv(), STEP))
            part = await asyncio.wait_for(client.recv(), STEP)
            assert text["data"]["msg*"] == part[:32].decode()
            got.append((text["data"]["msgID"], int.from_bytes(part[32:36], "little"), len(part) - 32))
        assert got == [(str(i), i, PART) for i in range(COUNT)]
        assert ns.session.outbox == 0 and ns.session.stats()["msgs_out"] == COUNT


async def test_a_closed_link_is_not_writable():
    async with Served() as srv:
        async with connect(srv.url) as client:
            await until(lambda: srv.namespaces and srv.namespaces[0].ws is not None, "the session")
            ws = srv.namespaces[0].ws
        await client.wait_closed()
        await until(lambda: not ws_cork.writable(ws), "the server side to see the close")
        assert not ws_cork.paused(ws)
        assert not ws_cork.corkable(object()) and not ws_cork.writable(object())


def test_binary_header_is_what_websockets_writes():
    """A large frame framed by ws_cork reads back, through websockets' own client parser, as
    the frame websockets would have written."""
    from websockets.frames import Frame, Opcode
    from rce_robot.ws_cork import binary_header
    for n in (0, 125, 126, 65535, 65536, 1_128_837):
        data = bytes(range(256)) * (n // 256) + bytes(n % 256)
        assert binary_header(n) + data == Frame(Opcode.BINARY, data).serialize(mask=False)


async def test_backlog_counts_frames_received_and_not_yet_read():
    got = asyncio.Event()
    seen: list[int] = []

    async def handler(ws) -> None:
        await got.wait()                        # the client's frames arrive while nobody reads
        await until(lambda: ws_cork.backlog(ws) == 3, "three frames waiting")
        for _ in range(3):
            await ws.recv()
            seen.append(ws_cork.backlog(ws))
    server = await serve(handler, "127.0.0.1", 0, compression=None)
    try:
        async with connect(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}/", compression=None) as client:
            for m in ("a", "b", "c"):
                await client.send(m)
            got.set()
            await until(lambda: len(seen) == 3, "the frames read")
        assert seen == [2, 1, 0] and ws_cork.backlog(object()) == 0
    finally:
        server.close()
        await server.wait_closed()


async def test_behind_counts_what_the_kernel_holds_too_until_everything_is_read():
    """A client writes 2000 frames at once. While the server has taken only some, the rest wait in
    websockets' queue or in the kernel (``unread``: FIONREAD); once it has taken the last one,
    nothing is behind."""
    n, firsts, last = 2000, [], []

    async def handler(ws) -> None:
        await ws.recv()
        firsts.append((ws_cork.behind(ws), ws_cork.unread(ws)))
        for _ in range(n - 1):
            await ws.recv()
        last.append((ws_cork.behind(ws), ws_cork.unread(ws)))
    server = await serve(handler, "127.0.0.1", 0, compression=None, max_queue=4)
    try:
        async with connect(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}/", compression=None) as client:
            ws_cork.write(client, ["x" * 1000] * n)
            await until(lambda: last, "the last frame read")
        assert firsts[0][0] > 0 and last == [(0, 0)]
        assert ws_cork.unread(object()) == 0 and ws_cork.behind(object()) == 0
    finally:
        server.close()
        await server.wait_closed()
