"""A data link across a thin link keeps its delay bounded, in network namespaces the test makes (root;
deleted after, also on failure): the sender in the root namespace, a reader in namespace R that reads
as fast as frames come, the root end of the veth pair shaped to 1 Mbit/s with HTB into a 40-packet FIFO
(one TCP segment a packet).

The sender offers a 40 kB frame every 0.1 s (3.2 Mbit/s, which the link cannot carry) for 8 s. A data
link lets its kernel and transport hold only what the link sends in a moment at its measured rate, so
the rest waits in the link's queue, where ``max_delay`` (1 s) drops what waited too long, counted: every
frame arrives within about 2 s of being offered (the queue's second, the FIFO's half second, and what
the socket holds) or is counted as dropped. With the kernel's 1 MiB of unsent bytes at this rate (8 s),
frames arrived up to 5 s late and none was dropped.
"""
from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
import time

import pytest

from rce.tools.netlab import NetLab
from rce.transport import framing
from rce.transport.link import FramedLink, nodelay

pytestmark = pytest.mark.asyncio

FRAME = 40_000            # bytes of payload a frame
PERIOD = 0.1              # s between frames
SEND_S = 8.0              # s of sending
LATE_BOUND = 2.5          # s: the queue's max_delay (1 s) + the 40-packet FIFO (~0.5 s) + the socket's + slack
WAIT = 30.0               # s any one step may take on a loaded machine

# the reader in R: accepts one link and prints, per DATA frame, its sequence number and how late it came
READER = r"""
import socket, struct, sys, time, json
from rce.transport import framing
srv = socket.socket(); srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
srv.bind(("0.0.0.0", 0)); srv.listen(1)
print(srv.getsockname()[1], flush=True)
conn, _ = srv.accept()
dec = framing.FrameDecoder(framing.DEFAULT_MAX_FRAME)
while True:
    buf = dec.get_buffer()
    n = conn.recv_into(buf)
    if not n:
        break
    for f in dec.buffer_updated(n):
        if isinstance(f, framing.DataFrame):
            seq, sent = struct.unpack_from("!Id", f.payload)
            print(json.dumps([seq, time.monotonic() - sent]), flush=True)
"""


async def test_a_stream_the_link_cannot_carry_arrives_late_by_at_most_the_queues_bound():
    with NetLab("dlt") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.shape(link, "a", "1mbit", queue=40, one_segment=True)
        reader = subprocess.Popen(lab.wrap("r", [sys.executable, "-c", READER]), stdout=subprocess.PIPE, text=True)
        try:
            port = int(await asyncio.wait_for(asyncio.to_thread(reader.stdout.readline), WAIT))
            r, w = await asyncio.open_connection(link.b_ip, port)
            nodelay(w, data=True)
            out = FramedLink(r, w, name="thin", on_frame=lambda f: None, data=True, max_delay=1.0).start()
            pad = bytes(FRAME - 12)
            t0, sent = time.monotonic(), 0
            while time.monotonic() - t0 < SEND_S:
                payload = struct.pack("!Id", sent, time.monotonic()) + pad
                out.offer(framing.encode_data_header(framing.MSG, 1, 2, 0, len(payload)), payload)
                sent += 1
                await asyncio.sleep(PERIOD)
            # what is still queued either goes within max_delay or is dropped: then the link is idle
            end = time.monotonic() + WAIT
            while (out.held or out.waiting) and time.monotonic() < end:
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.0)                    # the FIFO's last half second
            out.close()
            lines = (await asyncio.wait_for(asyncio.to_thread(reader.communicate), WAIT))[0].splitlines()
        finally:
            reader.kill()
            reader.wait()
    got = [json.loads(x) for x in lines]
    late = max(lag for _seq, lag in got)
    assert out.expired > 0, "a stream of 3.2 Mbit/s through 1 Mbit/s: some frames waited past max_delay"
    assert len(got) + out.dropped == sent, (len(got), out.dropped, sent)
    assert len({seq for seq, _ in got}) == len(got) and [s for s, _ in got] == sorted(s for s, _ in got)
    assert late < LATE_BOUND, f"a frame came {late:.2f} s after it was offered ({len(got)} of {sent} came)"
