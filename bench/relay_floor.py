"""The floor of a relayed round trip: the least any cloud engine that puts a process between a
robot and its node can take. Three processes on loopback, as rce's direct path has them
(robot client, rce-robot, node): this one (the client) -> a relay -> an echo -> the relay ->
the client, each hop a raw websocket (the ``websockets`` library on uvloop), each message the
ws anchor's JSON DM, forwarded as it came (no parse in the relay or the echo; the client parses
the reply, as the anchors do).

It counts what the topology costs: every round trip wakes three processes (the relay twice),
where ROS 1's direct TCPROS link wakes two and ``shared/anchors/ws_rtt.py`` (server and client
in one process) one.

Usage::

    .venv/bin/python bench/relay_floor.py [--sizes 3,1623,...] [--reps 20] [--gap S]

Prints one JSON line ``{"peer": "relay-floor", "gap_s", "rtt_ms": {size: median ms}}`` as the
anchors do (each timed round trip after ``--gap`` s of silence; one unmeasured round trip per
size first). ``--role echo|relay`` is how it starts its two helper processes.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time



async def _echo() -> None:
    import websockets

    async def echo(ws):
        async for m in ws:
            await ws.send(m)
    async with websockets.serve(echo, "127.0.0.1", 0, max_size=None, compression=None) as srv:
        print(srv.sockets[0].getsockname()[1], flush=True)
        await asyncio.Future()


async def _relay(upstream: int) -> None:
    import websockets

    async def pump(src, dst):
        try:
            async for m in src:
                await dst.send(m)
        except websockets.ConnectionClosed:
            pass

    async def relay(ws):
        async with websockets.connect(f"ws://127.0.0.1:{upstream}", max_size=None, compression=None) as up:
            tasks = [asyncio.create_task(pump(ws, up)), asyncio.create_task(pump(up, ws))]
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)   # one side closed: close the other
            for t in tasks:
                t.cancel()
    async with websockets.serve(relay, "127.0.0.1", 0, max_size=None, compression=None) as srv:
        print(srv.sockets[0].getsockname()[1], flush=True)
        await asyncio.Future()


def _spawn(*role: str) -> tuple[subprocess.Popen, int]:
    """Start this script in ``role``; returns the process and the port it printed (its first
    line; it exits, and the line is empty, when it cannot serve). Raises RuntimeError then."""
    p = subprocess.Popen([sys.executable, __file__, "--role", *role], stdout=subprocess.PIPE, text=True)
    line = p.stdout.readline()
    if not line.strip().isdigit():
        p.kill()
        raise RuntimeError(f"relay_floor --role {role[0]} did not start (exit {p.wait()}, printed {line!r})")
    return p, int(line)


async def measure_ws(port: int, sizes: list[int], reps: int, gap: float) -> dict:
    """Round trips of the ws anchor's JSON DM to a websocket echo at ``port`` on loopback: per
    size one unmeasured round trip, then ``reps`` timed ones (a quarter, at least 3, at >= 1 MB),
    each after ``gap`` s of silence; returns {size: median ms}."""
    import websockets
    out = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", max_size=None, compression=None) as ws:
        for size in sizes:
            msg = json.dumps({"type": "DM", "data": {"iTag": "x", "type": "std_msgs/String", "msgID": "",
                                                     "msg": {"data": "a" * size}}})
            await ws.send(msg)
            await ws.recv()
            samples = []
            for _ in range(reps if size < 1_000_000 else max(3, reps // 4)):
                if gap > 0:
                    await asyncio.sleep(gap)
                t0 = time.perf_counter()
                await ws.send(msg)
                json.loads(await ws.recv())
                samples.append((time.perf_counter() - t0) * 1000)
            out[size] = statistics.median(samples)
    return out


def _run(coro) -> None:
    try:
        import uvloop
        uvloop.run(coro)
    except ImportError:
        asyncio.run(coro)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", help="payload sizes, bytes, comma-separated (default: the anchors')")
    ap.add_argument("--reps", type=int, default=int(os.environ.get("REPS", "20")))
    ap.add_argument("--gap", type=float, default=0.0, help="s of silence before each timed round trip")
    ap.add_argument("--role", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role:
        _run(_echo() if args.role[0] == "echo" else _relay(int(args.role[1])))
        return 0
    if args.sizes:
        sizes = [int(s) for s in args.sizes.split(",")]
    else:
        from common import anchor_sizes
        sizes = anchor_sizes()
    echo, echo_port = _spawn("echo")
    try:
        relay, relay_port = _spawn("relay", str(echo_port))
        try:
            result: dict = {}

            async def go():
                result.update(await measure_ws(relay_port, sizes, args.reps, args.gap))
            _run(go())
        finally:
            relay.kill()
            relay.wait()
    finally:
        echo.kill()
        echo.wait()
    print(json.dumps({"peer": "relay-floor", "gap_s": args.gap, "rtt_ms": result}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
