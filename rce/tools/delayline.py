"""A link's propagation delay, in userspace: a transparent Ethernet bridge between two devices that
holds every frame a set time before it passes it on, both ways (what ``tc qdisc ... netem delay``
does, for kernels without ``netem``). :meth:`rce.tools.netlab.NetLab.link` puts one in the middle of
a link on request (``delay=True``), in a namespace of its own::

    python -m rce.tools.delayline DEV_A DEV_B --control PATH [--delay-ms 0] [--limit 4096]

The bridge reads each device with a raw ``AF_PACKET`` socket (``PACKET_IGNORE_OUTGOING``: not what it
sent itself) and writes the other; with ``PACKET_VNET_HDR`` on both, a frame's checksum and
segmentation-offload state (``struct virtio_net_hdr``) cross with it unchanged, so the end devices
keep their offloads. The rate stays the end devices' own (HTB on the sender's egress,
:meth:`~rce.tools.netlab.NetLab.shape`): a frame leaves its sender's queue at the link's rate, then
travels the delay, as on a real link.

Control: datagrams on the Unix socket ``PATH`` (``--control``), each answered with one JSON line:
``delay MS`` sets the delay of both directions (ms, from the next frame on; frames already held keep
their time, and no frame overtakes one held before it: a delay that shrinks waits for those held);
``stats`` asks for ``{"delay_ms", "forwarded", "dropped", "held"}``. The process prints ``ready`` once
the control socket is bound. It ends on SIGTERM or SIGINT.

Each direction holds at most ``--limit`` frames: a frame beyond that is dropped and counted
(``dropped``), as a link's queue that overflows.
"""
from __future__ import annotations

import argparse
import json
import os
import select
import signal
import socket
import sys
import time
from collections import deque

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
PACKET_IGNORE_OUTGOING = 23
PACKET_OUTGOING = 4               # sll_pkttype of a frame this host sent
MAX_FRAME = 65_536 + 10           # a segmentation-offload frame (64 KiB) and its virtio_net_hdr
LIMIT = 4096                      # frames each direction holds at most


class DelayQueue:
    """One direction's frames held for ``delay_s`` s (sans I/O: the caller gives the clock).

    Frames leave in the order they came (FIFO), each no earlier than ``delay_s`` after it came in; at
    most ``limit`` are held, and a frame beyond that is dropped and counted in :attr:`dropped`."""

    def __init__(self, delay_s: float = 0.0, limit: int = LIMIT):
        if delay_s < 0:
            raise ValueError(f"delay {delay_s} s: must be >= 0")
        self.delay_s = delay_s
        self.limit = limit
        self.held: deque[tuple[float, bytes]] = deque()
        self.dropped = 0
        self.forwarded = 0

    def push(self, now: float, frame: bytes) -> bool:
        """Hold ``frame``, which came in at ``now`` (s); False when the queue is full (dropped, counted)."""
        if len(self.held) >= self.limit:
            self.dropped += 1
            return False
        due = now + self.delay_s
        if self.held and self.held[-1][0] > due:
            due = self.held[-1][0]            # never ahead of one held before it
        self.held.append((due, frame))
        return True

    def next_due(self) -> float | None:
        """When the oldest held frame is due (s), or None when none is held."""
        return self.held[0][0] if self.held else None

    def pop_due(self, now: float) -> list[bytes]:
        """The frames due at ``now`` (s), oldest first, no longer held."""
        out = []
        while self.held and self.held[0][0] <= now:
            out.append(self.held.popleft()[1])
        self.forwarded += len(out)
        return out


def open_device(dev: str) -> socket.socket:
    """A non-blocking raw socket on ``dev`` that reads what arrives on it (not what this host sends on
    it) and writes frames out of it, each with its ``virtio_net_hdr``. Raises OSError (no such device,
    not root)."""
    s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    s.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
    s.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    s.bind((dev, ETH_P_ALL))
    s.setblocking(False)
    return s


def serve(dev_a: str, dev_b: str, control: str, delay_ms: float, limit: int) -> None:
    """Bridge ``dev_a`` and ``dev_b`` with ``delay_ms`` ms each way until SIGTERM or SIGINT; answer
    control datagrams on the Unix socket ``control`` (module doc)."""
    a, b = open_device(dev_a), open_device(dev_b)
    ways = {a: (DelayQueue(delay_ms / 1e3, limit), b), b: (DelayQueue(delay_ms / 1e3, limit), a)}
    ctl = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if os.path.exists(control):
        os.unlink(control)
    ctl.bind(control)
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    print("ready", flush=True)
    try:
        while not stop:
            dues = [d for d in (q.next_due() for q, _ in ways.values()) if d is not None]
            timeout = max(0.0, min(dues) - time.monotonic()) if dues else 0.5
            try:
                readable, _, _ = select.select([a, b, ctl], [], [], timeout)
            except InterruptedError:
                continue
            now = time.monotonic()
            for s in readable:
                if s is ctl:
                    _answer(ctl, ways)
                    continue
                q = ways[s][0]
                while True:
                    try:
                        frame, addr = s.recvfrom(MAX_FRAME)
                    except BlockingIOError:
                        break
                    if addr[2] != PACKET_OUTGOING:
                        q.push(now, frame)
            now = time.monotonic()
            for q, out in ways.values():
                for frame in q.pop_due(now):
                    try:
                        out.send(frame)
                    except OSError:           # the device is down or its queue full: lost, as on a wire
                        q.dropped += 1
    finally:
        ctl.close()
        _unlink(control)


def _answer(ctl: socket.socket, ways: dict) -> None:
    """Answer one control datagram (module doc)."""
    try:
        msg, peer = ctl.recvfrom(512)
    except BlockingIOError:
        return
    words = msg.decode(errors="replace").split()
    queues = [q for q, _ in ways.values()]
    try:
        if words[:1] == ["delay"] and len(words) == 2:
            ms = float(words[1])
            if not ms >= 0:
                raise ValueError(f"delay {ms} ms: must be >= 0")
            for q in queues:
                q.delay_s = ms / 1e3
        elif words != ["stats"]:
            raise ValueError(f"unknown request {msg[:80]!r}: expected 'delay MS' or 'stats'")
        reply = {"delay_ms": queues[0].delay_s * 1e3, "forwarded": sum(q.forwarded for q in queues),
                 "dropped": sum(q.dropped for q in queues), "held": sum(len(q.held) for q in queues)}
    except ValueError as e:
        reply = {"error": str(e)}
    if peer:
        try:
            ctl.sendto(json.dumps(reply).encode(), peer)
        except OSError:
            pass                               # the asker is gone


def _unlink(path: str) -> None:
    """Remove ``path`` if it is there."""
    try:
        os.unlink(path)
    except OSError:
        pass


def request(control: str, words: str, timeout: float = 5.0) -> dict:
    """Send ``words`` (``delay MS`` or ``stats``) to the delay line on ``control`` and return its answer.
    Raises RuntimeError with the line's own reason when it refuses, OSError/TimeoutError when it is not
    there."""
    me = f"{control}.{os.getpid()}.{time.monotonic_ns()}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        s.bind(me)
        s.settimeout(timeout)
        s.sendto(words.encode(), control)
        reply = json.loads(s.recv(4096))
    finally:
        s.close()
        _unlink(me)
    if "error" in reply:
        raise RuntimeError(f"delay line {control}: {reply['error']}")
    return reply


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dev_a")
    p.add_argument("dev_b")
    p.add_argument("--control", required=True, help="Unix datagram socket to take requests on")
    p.add_argument("--delay-ms", type=float, default=0.0, help="each direction's delay (ms)")
    p.add_argument("--limit", type=int, default=LIMIT, help="frames each direction holds at most")
    a = p.parse_args(argv)
    if a.delay_ms < 0:
        p.error(f"--delay-ms {a.delay_ms}: must be >= 0")
    serve(a.dev_a, a.dev_b, a.control, a.delay_ms, a.limit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
