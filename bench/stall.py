"""Stalled node: a camera-rate stream into a container node that is frozen for a while, with
ROS 1 in the same run.

A robot publishes ``std_msgs/String`` messages of ``--size`` bytes (default 1 MB, an image) at
``--rate`` Hz (30, a camera) through a SubscriberForwarder to ``Test/stringEcho.py`` in a
container, which echoes each back through a PublisherForwarder (``bench/rtt.py``'s
``rce_forwarder`` path, the node's direct links up). Each payload starts with the message's
sequence number. After ``--warmup`` s the echo node is stopped with SIGSTOP for ``--stall`` s
(a node stuck in a long computation, held in a debugger, or throttled by its container's CPU
quota), then continued, while the robot keeps publishing for ``--after`` s.

Measured per system, from the echoes the robot gets (age = the echo's arrival minus its
message's send time, one clock):

- ``max_age_s``: the oldest echo after the node was continued: how stale the data the node was
  handed had become;
- ``stale``: echoes after the node was continued that were older than ``--stale`` s (0.5): old
  messages the node had to work through before it saw live data again;
- ``fresh_after_s``: from SIGCONT to the last echo older than ``--stale`` s;
- ``lost``: messages published whose echo never came (within ``--drain`` s after the end).

The peer: ``bench/ros1/stall.py`` (rospy, TCPROS, publisher ``queue_size`` 10, the same
message, rate, payload and timeline), run with the system python3 after the rce run.

Usage::

    .venv/bin/python bench/stall.py [--size B] [--rate HZ] [--warmup S] [--stall S] [--after S]
        [--stale S] [--no-ros1] [--json PATH] [--plot PATH]

Results: ``bench/results/stall.json`` and ``bench/results/stall.png`` (age of every echo
against time, the stall shaded).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import time
import uuid
from pathlib import Path

from common import (BENCH, RESULTS, SYS_PY, RawRobot, console, engine, ensure_ros1, git_head, pyplot,
                    write_json)
from rtt import STRING, ros1_string, setup_echo
from rtt_cpu import direct_routes, processes

SEQ_DIGITS = 10          # the payload's first characters: the message's sequence number
CTAG = "stallC"


class Stream:
    """The robot's side on one websocket: publishes at ``rate`` Hz, records every echo."""

    def __init__(self, r: RawRobot, req: str, size: int, rate: float):
        self.r, self.req, self.size, self.rate = r, req, size, rate
        self.sent: list[tuple[int, float]] = []
        self.echoes: list[tuple[int, float]] = []
        self.filler = "a" * max(0, size - SEQ_DIGITS)

    def frames(self, seq: int) -> list:
        ref = uuid.uuid4().hex
        return [json.dumps({"type": "DM", "data": {"iTag": self.req, "type": STRING, "msgID": "", "msg*": ref}}),
                ref.encode() + ros1_string(f"{seq:0{SEQ_DIGITS}d}" + self.filler)]

    async def receive(self) -> None:
        """Every binary part the robot gets is an echo: its message's sequence number is the
        first digits after the reference (32 bytes) and the length (4)."""
        while True:
            m = await self.r.ws.recv()
            if isinstance(m, bytes) and len(m) >= 36 + SEQ_DIGITS:
                self.echoes.append((int(m[36:36 + SEQ_DIGITS]), time.monotonic()))

    async def first_echo(self, timeout: float = 30.0) -> None:
        """Publish message 0 until its echo comes (the node is wired both ways)."""
        deadline = time.monotonic() + timeout
        while not self.echoes:
            if time.monotonic() > deadline:
                raise RuntimeError(f"no echo within {timeout:g} s")
            for f in self.frames(0):
                await self.r.ws.send(f)
            await asyncio.sleep(0.2)     # one try per 0.2 s while the wiring completes

    async def publish(self, seconds: float, first_seq: int) -> int:
        """Publish for ``seconds`` at the rate (on schedule: a late send does not shift the
        rest); returns the next sequence number."""
        loop = asyncio.get_running_loop()
        t0, seq, period = loop.time(), first_seq, 1.0 / self.rate
        while loop.time() - t0 < seconds:
            frames = self.frames(seq)
            self.sent.append((seq, time.monotonic()))
            for f in frames:
                await self.r.ws.send(f)
            seq += 1
            await asyncio.sleep(max(0.0, t0 + (seq - first_seq) * period - loop.time()))
        return seq


async def run_rce(a) -> dict:
    """The rce run on a fresh engine; ``{"sent", "echoes", "t_stop", "t_cont"}`` as the peer's."""
    with engine() as eng:
        async with RawRobot(eng.master_url, "stallR") as r:
            req, _resp = await setup_echo(r, CTAG, "Forwarder")
            s = Stream(r, req, a.size, a.rate)
            rx = asyncio.create_task(s.receive())
            try:
                await s.first_echo()
                await direct_routes(eng, CTAG)
                node = processes([q.pid for q in eng.procs], str(eng.workdir))["node"]
                if len(node) != 1:
                    raise RuntimeError(f"expected one echo node process, found {len(node)}")
                pid = node[0].pid
                await asyncio.sleep(0.5)          # the wiring echoes are in
                s.echoes.clear()
                seq = await s.publish(a.warmup, 1)
                os.kill(pid, signal.SIGSTOP)
                t_stop = time.monotonic()
                try:
                    seq = await s.publish(a.stall, seq)
                finally:
                    os.kill(pid, signal.SIGCONT)
                t_cont = time.monotonic()
                await s.publish(a.after, seq)
                await asyncio.sleep(a.drain)      # the last echoes may come this late
            finally:
                rx.cancel()
    return {"peer": "rce", "sent": s.sent, "echoes": s.echoes, "t_stop": t_stop, "t_cont": t_cont}


def run_ros1(a) -> dict:
    """The peer (bench/ros1/stall.py under the system python3)."""
    r = subprocess.run([SYS_PY, str(BENCH / "ros1" / "stall.py"), "--size", str(a.size), "--rate", str(a.rate),
                        "--warmup", str(a.warmup), "--stall", str(a.stall), "--after", str(a.after),
                        "--drain", str(a.drain)], capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        raise RuntimeError(f"bench/ros1/stall.py failed ({r.returncode}): {r.stderr[-800:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def summarize(run: dict, stale: float) -> dict:
    """The measures of the module doc from one run's ``sent``/``echoes``/``t_cont``; the echo
    ``series`` as ``[t - t_cont, age]`` for the plot."""
    sent = dict(run["sent"])
    t_cont = run["t_cont"]
    echoes = [(seq, t, t - sent[seq]) for seq, t in run["echoes"] if seq in sent]
    after = [(seq, t, age) for seq, t, age in echoes if t >= t_cont]
    old = [(t, age) for _seq, t, age in after if age > stale]
    got = {seq for seq, _t, _a in echoes}
    return {"sent": len(sent), "echoed": len(got), "lost": len(sent) - len(got),
            "max_age_s": round(max((age for *_, age in after), default=0.0), 3),
            "stale": len(old), "fresh_after_s": round(max((t for t, _ in old), default=t_cont) - t_cont, 3),
            "stall_s": round(t_cont - run["t_stop"], 3),
            "series": [[round(t - t_cont, 4), round(age, 4)] for _seq, t, age in echoes]}


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for name, r in res["systems"].items():
        xs, ys = zip(*r["series"], strict=True) if r["series"] else ((), ())
        ax.plot(xs, ys, ".", ms=3, label=f"{name}: {r['stale']} stale, fresh after {r['fresh_after_s']:.2f} s, "
                                          f"{r['lost']} lost")
    stall = max(r["stall_s"] for r in res["systems"].values())
    ax.axvspan(-stall, 0, color="0.9", label="node stopped (SIGSTOP)")
    ax.axhline(res["stale_s"], color="0.6", lw=0.8, ls="--")
    ax.set_xlabel("echo arrival, s after the node was continued")
    ax.set_ylabel("age of the echoed message, s")
    ax.set_title(f"{res['size']} B at {res['rate']:g} Hz into a node stopped {stall:.1f} s")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=1_000_000, help="payload bytes (default 1 MB)")
    p.add_argument("--rate", type=float, default=30.0, help="messages per second (default 30)")
    p.add_argument("--warmup", type=float, default=2.0, help="s of streaming before the stall (default 2)")
    p.add_argument("--stall", type=float, default=3.0, help="s the node is stopped (default 3)")
    p.add_argument("--after", type=float, default=4.0, help="s of streaming after it is continued (default 4)")
    p.add_argument("--drain", type=float, default=3.0, help="s to wait for the last echoes (default 3)")
    p.add_argument("--stale", type=float, default=0.5, help="an echo older than this is stale, s (default 0.5)")
    p.add_argument("--no-ros1", action="store_true", help="skip the ROS 1 peer")
    p.add_argument("--json", type=Path, default=RESULTS / "stall.json")
    p.add_argument("--plot", type=Path, default=RESULTS / "stall.png")
    return p.parse_args(argv)


def main(argv=None) -> int:
    a = parse_args(argv)
    con = console()
    runs = {}
    with con.status("rce: streaming, stopping the node, continuing it"):
        runs["rce"] = asyncio.run(run_rce(a))
    con.print("rce done")
    if not a.no_ros1:
        ok, why = ensure_ros1(log=con.print)
        if ok:
            with con.status("ROS 1: the same"):
                runs["ros1"] = run_ros1(a)
            con.print("ROS 1 done")
        else:
            con.print(f"[yellow]ROS 1 skipped: {why}")
    res = {"size": a.size, "rate": a.rate, "warmup_s": a.warmup, "stall_s": a.stall, "after_s": a.after,
           "stale_s": a.stale, "commit": git_head(),
           "systems": {name: summarize(r, a.stale) for name, r in runs.items()}}
    for name, r in res["systems"].items():
        con.print(f"{name:5}: sent {r['sent']}, lost {r['lost']}; after the node was continued: oldest echo "
                  f"{r['max_age_s']:.2f} s, {r['stale']} echoes older than {a.stale:g} s, fresh after "
                  f"{r['fresh_after_s']:.2f} s")
    write_json(a.json, res)
    plot(res, a.plot)
    con.print(f"results: {a.json}  plot: {a.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
