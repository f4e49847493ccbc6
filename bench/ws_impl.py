"""The robot endpoint's websocket library: picows (a Cython websocket implementation for asyncio,
rce-robot's default) against websockets (``rce-robot --ws-impl websockets``, with the corked writes
of :mod:`rce_robot.ws_cork`), each as an echo server on uvloop in its own process, measured in the
same run.

Each server echoes every frame it gets straight back (text as text, binary as binary). The client
(one process, websockets on uvloop, the same for both servers) sends what a forwarder robot sends
for one pose: a DM text frame (~150 B) and its binary part (~370 B), and measures:

- ``server_us_per_msg``: the server process's CPU (user + system, psutil) over ``--n`` poses sent
  pipelined (``--window`` in flight), per frame echoed;
- ``rtt_ms``: the median of ``--rtts`` lone round trips of one pose (send both frames, wait for
  both back), and the same after ``--gap`` s of silence (``rtt_gap_ms``).

``picows_over_websockets`` gives each picows number over the websockets one. The server under test
is the only thing that differs; the client's CPU is in neither number.

Usage::

    .venv/bin/python bench/ws_impl.py [--n 20000] [--window 64] [--rtts 300] [--gap 0.2] [--json PATH]
        [--plot PATH]

Results: a table, ``bench/results/ws_impl.json`` and ``bench/results/ws_impl.png``.
"""
from __future__ import annotations

import argparse
import asyncio
import multiprocessing as mp
import sys
import time
from pathlib import Path

from common import RESULTS, console, free_port, median, process_cpu_s, pyplot, ratio, write_json

TEXT = ('{"type":"DM","data":{"iTag":"amclPoseSender_1","type":"geometry_msgs/PoseWithCovarianceStamped",'
        '"msgID":"","msg*":"%032x"}}')
BINARY_LEN = 372            # bytes of a pose's binary part: 32-byte id + 340-byte PoseWithCovarianceStamped
IMPLS = ("websockets", "picows")


# -- the servers (each in its own process) -----------------------------------------------------------
async def _websockets_server(port: int, ready) -> None:
    from websockets.asyncio.server import serve
    from websockets.exceptions import ConnectionClosed

    from rce_robot import ws_cork

    async def echo(ws) -> None:
        try:
            async for frame in ws:
                if not ws_cork.writable(ws):
                    await ws.drain()
                ws_cork.write(ws, (frame,))
        except ConnectionClosed:
            pass
    async with serve(echo, "127.0.0.1", port, max_size=None, compression=None, ping_interval=None,
                     max_queue=64):
        ready.send("ready")
        await asyncio.Future()


async def _picows_server(port: int, ready) -> None:
    from picows import WSListener, WSMsgType, ws_create_server

    class Echo(WSListener):
        def on_ws_frame(self, transport, frame) -> None:
            if frame.msg_type == WSMsgType.CLOSE:
                transport.send_close(frame.get_close_code())
                transport.disconnect()
            elif frame.msg_type in (WSMsgType.TEXT, WSMsgType.BINARY):
                transport.send(frame.msg_type, frame.get_payload_as_memoryview())
    server = await ws_create_server(lambda _request: Echo(), "127.0.0.1", port, max_frame_size=64 * 1024 * 1024)
    ready.send("ready")
    async with server:
        await asyncio.Future()


def server_main(impl: str, port: int, ready) -> None:
    """Entry point of a server process: serve ``impl``'s echo on ``port``, say ``ready``."""
    from rce.plumbing.process import run_loop
    try:
        run_loop((_websockets_server if impl == "websockets" else _picows_server)(port, ready))
    except KeyboardInterrupt:
        pass


# -- the client ----------------------------------------------------------------------------------------
async def measure(port: int, pid: int, n: int, window: int, rtts: int, gap: float) -> dict:
    """Round trips, then pipelined poses, against the server on ``port`` (process ``pid``)."""
    import psutil
    from websockets.asyncio.client import connect
    proc = psutil.Process(pid)
    body = bytes(BINARY_LEN)
    async with connect(f"ws://127.0.0.1:{port}/", max_size=None, compression=None, ping_interval=None,
                       max_queue=None) as ws:
        async def one(i: int) -> float:
            t0 = time.perf_counter()
            await ws.send(TEXT % i)
            await ws.send(body)
            await ws.recv()
            await ws.recv()
            return (time.perf_counter() - t0) * 1e3
        for i in range(50):                      # warm-up
            await one(i)
        rtt = [await one(i) for i in range(rtts)]
        lone = []
        for i in range(max(3, rtts // 30)):
            await asyncio.sleep(gap)             # the gap itself is what is measured after
            lone.append(await one(i))
        got = 0
        done = asyncio.Event()

        async def reader() -> None:
            nonlocal got
            async for _ in ws:
                got += 1
                if got == 2 * n:
                    done.set()
                    return
        c0 = process_cpu_s(proc)
        rd = asyncio.create_task(reader())
        w0 = time.perf_counter()
        for i in range(n):
            await ws.send(TEXT % i)
            await ws.send(body)
            if got < 2 * (i - window):           # at most ``window`` poses in flight
                await asyncio.sleep(0)
        await asyncio.wait_for(done.wait(), 120)
        wall = time.perf_counter() - w0
        c1 = process_cpu_s(proc)
        await rd
    return {"rtt_ms": median(rtt), "rtt_gap_ms": median(lone), "server_us_per_msg": (c1 - c0) * 1e6 / (2 * n),
            "poses_per_s": n / wall, "server_cores": (c1 - c0) / wall}


def run_one(impl: str, args) -> dict:
    ctx = mp.get_context("spawn")
    port = free_port()
    r, w = ctx.Pipe(duplex=False)
    p = ctx.Process(target=server_main, args=(impl, port, w), daemon=True)
    p.start()
    try:
        if not r.poll(30):
            raise RuntimeError(f"the {impl} server did not start")
        r.recv()
        from rce.plumbing.process import run_loop
        return run_loop(measure(port, p.pid, args.n, args.window, args.rtts, args.gap))
    finally:
        p.terminate()
        p.join(5)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=20000, help="poses sent pipelined per server (default 20000)")
    p.add_argument("--window", type=int, default=64, help="poses in flight at most (default 64)")
    p.add_argument("--rtts", type=int, default=300, help="lone round trips per server (default 300)")
    p.add_argument("--gap", type=float, default=0.2, help="s of silence before each gap round trip (default 0.2)")
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds of both servers; medians (default 3)")
    p.add_argument("--json", type=Path, default=RESULTS / "ws_impl.json")
    p.add_argument("--plot", type=Path, default=RESULTS / "ws_impl.png")
    args = p.parse_args(argv)
    con = console()
    rounds: dict[str, list[dict]] = {i: [] for i in IMPLS}
    for k in range(args.rounds):
        for impl in IMPLS:
            rounds[impl].append(run_one(impl, args))
            con.print(f"round {k + 1}/{args.rounds} {impl}: " + ", ".join(f"{key} {v:.4g}" for key, v
                                                                       in rounds[impl][-1].items()))
    keys = ("server_us_per_msg", "rtt_ms", "rtt_gap_ms", "poses_per_s")
    res = {"n": args.n, "window": args.window, "rtts": args.rtts, "gap_s": args.gap, "rounds": rounds,
           **{impl: {k: median(r[k] for r in rounds[impl]) for k in keys} for impl in IMPLS}}
    res["picows_over_websockets"] = {k: round(ratio(res["picows"][k], res["websockets"][k]), 3) for k in keys}
    write_json(args.json, res)
    from rich.table import Table
    t = Table(title="echo server on uvloop: websockets (+ ws_cork) vs picows, medians of "
                    f"{args.rounds} rounds")
    for c in ("", *keys):
        t.add_column(c, justify="right")
    for row in (*IMPLS, "picows_over_websockets"):
        t.add_row(row, *[f"{res[row][k]:.4g}" for k in keys])
    con.print(t)
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.5))
    for ax, k, lab in zip(axes, keys[:3], ("server CPU us per frame", "round trip ms", "round trip after a gap ms"),
                          strict=True):
        ax.bar(IMPLS, [res[i][k] for i in IMPLS], color=("tab:blue", "tab:orange"))
        ax.set_title(lab, fontsize=9)
    fig.tight_layout()
    args.plot.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.plot, dpi=100)
    con.print(f"results: {args.json}  plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
