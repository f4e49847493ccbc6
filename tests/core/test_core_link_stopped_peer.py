"""rce.transport.link under a real fault: the peer process is frozen (SIGSTOP) while messages keep coming.

A reader process takes a TCP link on loopback and prints what arrives; the test offers a
message every millisecond (the rate of a fast sensor topic) and stops the reader with SIGSTOP.
While it is stopped the kernel's socket buffers fill, then the link's queue; once the reader is
continued it must get the newest messages and the control frame sent meanwhile, in order, and
every message not delivered must be counted as dropped, most of them as expired (older than
``max_delay``): a frozen node never makes the engine hold an ever older backlog."""
from __future__ import annotations

import asyncio
import os
import signal
import sys

from rce.transport import framing
from rce.transport.link import FramedLink

STEP = 10.0             # s, the longest any single wait may take
PAYLOAD = 16 * 1024     # bytes per message: the kernel's buffers fill within a few hundred
MAX_DELAY = 0.2         # s a message may wait in the link's queue

READER = r"""
import asyncio, sys
from rce.transport import framing
from rce.transport.link import FramedLink

async def main(port):
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    done = asyncio.Event()

    def on_frame(f):
        if isinstance(f, dict):
            print("control", f["mark"], flush=True)
            if f["mark"] == "end":
                done.set()
        else:
            print("msg", f.src, flush=True)
    FramedLink(reader, writer, name="test", on_frame=on_frame).start()
    print("ready", flush=True)
    await done.wait()

asyncio.run(main(int(sys.argv[1])))
"""


async def test_a_stopped_reader_gets_the_newest_messages_and_the_rest_are_counted():
    accepted: asyncio.Queue = asyncio.Queue()
    server = await asyncio.start_server(lambda r, w: accepted.put_nowait((r, w)), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    child = await asyncio.create_subprocess_exec(sys.executable, "-c", READER, str(port),
                                                 stdout=asyncio.subprocess.PIPE)
    try:
        assert (await asyncio.wait_for(child.stdout.readline(), STEP)).strip() == b"ready"
        r, w = await asyncio.wait_for(accepted.get(), STEP)
        link = FramedLink(r, w, name="reader", on_frame=lambda f: None, max_delay=MAX_DELAY).start()
        body = b"x" * PAYLOAD

        def offer(seq: int) -> None:
            assert link.offer(framing.encode_data_header(framing.MSG, 1, seq, 0, PAYLOAD), body)

        os.kill(child.pid, signal.SIGSTOP)
        seq = 0
        while link.expired < 50:            # until the queue has dropped messages for their age
            offer(seq)
            seq += 1
            await asyncio.sleep(0.001)      # a 1 kHz publisher
            assert seq < 100_000, "the link never held nor expired a message"
        link.send(framing.encode_control({"mark": "during"}))
        for _ in range(5):
            offer(seq)
            seq += 1
        os.kill(child.pid, signal.SIGCONT)
        link.send(framing.encode_control({"mark": "end"}))
        lines = []
        while not lines or lines[-1] != "control end":
            line = await asyncio.wait_for(child.stdout.readline(), STEP)
            assert line, f"the reader ended early after {lines[-3:]}"
            lines.append(line.decode().strip())
    finally:
        if child.returncode is None:
            os.kill(child.pid, signal.SIGCONT)
            child.kill()
        await child.wait()
        server.close()

    got = [int(x.split()[1]) for x in lines if x.startswith("msg ")]
    assert got == sorted(set(got)), "messages came out of order or twice"
    assert got[-5:] == list(range(seq - 5, seq)), "the newest messages did not arrive"
    assert lines.index("control during") == len(lines) - 7      # in its place: after the queue, before the last five
    assert len(got) + link.dropped == seq, "a message was lost without being counted"
    assert link.expired >= 50 and link.held == 0
    gaps = [b for a, b in zip(got, got[1:], strict=False) if b != a + 1]
    assert gaps, "nothing was dropped: the reader was never behind"
