"""Round-trip time robot -> container node -> robot against payload size, with the peers in
the same run.

Paths (the real engine as processes on loopback, the raw wire protocol as a robot speaks it):

- ``rce_converter``: DM with a JSON ``std_msgs/String`` -> SubscriberConverter ->
  container ``/stringEchoReq`` -> ``Test/stringEcho.py`` -> ``/stringEchoResp`` ->
  PublisherConverter -> DM back (JSON).
- ``rce_forwarder``: the same through forwarders: the DM carries the ROS 1 serialized
  ``std_msgs/String`` as the binary part ``msg*``.
- ``rce_c2c``: container to container, through forwarders: robot -> container A
  (``/relay``) -> interface link A -> B -> ``stringEcho`` in B -> robot. Its difference
  to ``rce_forwarder`` is the cost of the extra container hop.

Peers: ``ros1`` = ``shared/anchors/ros1_rtt.py`` (Debian's rospy, single master, TCPROS;
installed with apt-get when missing and running as root), ``ws_floor`` =
``shared/anchors/ws_rtt.py`` (raw websockets echo of the same JSON DM: the transport floor),
``relay_floor`` = ``bench/relay_floor.py`` (the same echo behind a relay process: client,
relay and echo are three processes, as robot, rce-robot and node are; the floor of the
topology, which wakes three processes per round trip where ROS 1 wakes two).
The anchors report medians only; rce paths report median and p90 (and p10 in the JSON: on a
busy machine, rce's many process hops make its median drift up with other load, while p10
stays near the uncontended cost).

The rce paths take turns size by size: for each size, one block of back-to-back repetitions
per path, after one unmeasured round trip of that size (the processes are hot, as in the
anchors' loops). ``machine_load`` in the JSON tells, per phase, how many cores other processes
(not this bench's) kept busy: the peers and rce run one after the other, so load from elsewhere
perturbs their ratios; ``--rounds K`` repeats everything K times and keeps, for every series
and size alike, the lowest of the K values (the least disturbed round). Each rce round trip is
timed from just before the first frame is sent to the reply parsed
(JSON decoded; for forwarders the JSON frame and its binary part both received), the
outgoing frames built beforehand, as the ws anchor does.

Sparse messages (``--gap S``): every timed round trip (rce, ROS 1 and the floor alike) comes
after S s of silence of the whole system, as a goal or a cancelGoal does, so each process on the
path has gone idle and must wake up. The ROS 1 peer is then ``bench/ros1_peer.py`` (the
anchor's topology and message, plus the gap; the anchor itself has none), and the floor is
the ws anchor's echo run in this process with the same gap. ``--gap 0`` measures with these
two peers back to back (they agree with the anchors). The results go to ``rtt_gap<S>.json`` /
``.png`` unless ``--json`` / ``--plot`` say otherwise.

Usage::

    .venv/bin/python bench/rtt.py [--sizes 3,1623,...] [--reps N] [--no-ros1] [--no-ws] [--no-relay]
        [--paths converter,forwarder,c2c] [--rounds K] [--nice N] [--wait-quiet S]
        [--gap S] [--json PATH] [--plot PATH]

``REPS`` (environment, default 20) sets the repetitions per size like the anchors (a quarter,
at least 3, for sizes >= 1 MB); ``--reps`` overrides it.
Results: ``bench/results/rtt.json`` and ``bench/results/rtt.png`` by default.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

from common import (BENCH, ForeignLoad, RawRobot, RESULTS, SYS_PY, VENV_PY, add_ws_impl_argument, anchor_sizes,
                    console, engine, ensure_ros1, fmt_ms, fmt_ratio, fmt_size, free_port, geomean, median, peer_result,
                    percentile, progress, pyplot, ratio, run_anchor, set_nice, wait_quiet, write_json)

PATHS = ("converter", "forwarder", "c2c")
STRING = "std_msgs/String"


def reps_for(size: int, reps: int) -> int:
    """As the anchors: REPS per size, a quarter (at least 3) from 1 MB up."""
    return reps if size < 1_000_000 else max(3, reps // 4)


def ros1_string(payload: str) -> bytes:
    """ROS 1 serialization of std_msgs/String: uint32 length + bytes."""
    b = payload.encode()
    return len(b).to_bytes(4, "little") + b


# -- setting up the paths --------------------------------------------------------------------

async def setup_echo(r: RawRobot, ctag: str, side: str) -> tuple[str, str]:
    """Container ``ctag`` with Test/stringEcho.py, robot-side interfaces of ``side``
    (Converter/Forwarder); returns (request iTag, response iTag)."""
    rid = r.robot
    await r.send("CC", {"containerTag": ctag})
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
               addInterfaces=[
                   {"endpointTag": ctag, "interfaceTag": "req", "interfaceType": "PublisherInterface",
                    "className": STRING, "addr": "/stringEchoReq"},
                   {"endpointTag": ctag, "interfaceTag": "resp", "interfaceType": "SubscriberInterface",
                    "className": STRING, "addr": "/stringEchoResp"},
                   {"endpointTag": rid, "interfaceTag": "req", "interfaceType": f"Subscriber{side}",
                    "className": STRING},
                   {"endpointTag": rid, "interfaceTag": "resp", "interfaceType": f"Publisher{side}",
                    "className": STRING}])
    await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in ("req", "resp")]})
    await r.wait_up("req", "resp")
    return "req", "resp"


async def setup_c2c(r: RawRobot, prefix: str) -> tuple[str, str]:
    """robot -> A:/relay -> (A/toB -> B/fromA) -> B:/stringEchoReq -> echo -> B:/stringEchoResp -> robot."""
    a, b, rid = f"{prefix}A", f"{prefix}B", r.robot
    await r.send("CC", {"containerTag": a})
    await r.send("CC", {"containerTag": b})
    ifs = [(a, "in", "PublisherInterface", "/relay"), (a, "toB", "SubscriberInterface", "/relay"),
           (b, "fromA", "PublisherInterface", "/stringEchoReq"), (b, "out", "SubscriberInterface", "/stringEchoResp"),
           (rid, "in", "SubscriberForwarder", None), (rid, "out", "PublisherForwarder", None)]
    await r.cn(addNodes=[{"containerTag": b, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
               addInterfaces=[{"endpointTag": e, "interfaceTag": t, "interfaceType": k, "className": STRING,
                               **({"addr": ad} if ad else {})} for e, t, k, ad in ifs])
    await r.send("CX", {"connect": [{"tagA": f"{a}/in", "tagB": f"{rid}/in"},
                                    {"tagA": f"{a}/toB", "tagB": f"{b}/fromA"},
                                    {"tagA": f"{b}/out", "tagB": f"{rid}/out"}]})
    await r.wait_up("in", "out")
    return "in", "out"


# -- one round trip ------------------------------------------------------------------------------

class Path_:
    """One measured path on one robot connection: ``prepare(size)`` builds the outgoing frames,
    ``roundtrip(frames, size, timeout)`` sends them and waits for the echo; returns ms or NaN."""

    def __init__(self, r: RawRobot, kind: str, req: str, resp: str):
        self.r, self.kind, self.req, self.resp = r, kind, req, resp
        self.binary = kind != "converter"

    def prepare(self, size: int) -> list:
        data = "a" * size
        if not self.binary:
            return [json.dumps({"type": "DM", "data": {"iTag": self.req, "type": STRING, "msgID": "",
                                                       "msg": {"data": data}}})]
        ref = uuid.uuid4().hex
        return [json.dumps({"type": "DM", "data": {"iTag": self.req, "type": STRING, "msgID": "", "msg*": ref}}),
                ref.encode() + ros1_string(data)]

    async def roundtrip(self, frames: list, size: int, timeout: float) -> float:
        ws, loop = self.r.ws, asyncio.get_running_loop()
        t0 = time.perf_counter()
        for f in frames:
            await ws.send(f)
        dm, parts = None, {}
        try:
            async with asyncio.timeout_at(loop.time() + timeout):    # no task per recv, as wait_for makes
                while True:
                    m = await ws.recv()
                    if isinstance(m, str):
                        d = json.loads(m)
                        if d.get("type") != "DM" or d["data"].get("iTag") != self.resp:
                            continue
                        if not self.binary:
                            if len(d["data"]["msg"]["data"]) == size:
                                return (time.perf_counter() - t0) * 1000
                            continue       # a late echo of an earlier message
                        dm = d["data"]
                    else:
                        parts[m[:32].decode()] = m
                    if dm is not None and dm.get("msg*") in parts:
                        if len(parts[dm["msg*"]]) == 32 + 4 + size:
                            return (time.perf_counter() - t0) * 1000
                        dm, parts = None, {}
        except (TimeoutError, asyncio.TimeoutError):
            return float("nan")

    async def drain(self, quiet: float = 0.3) -> None:
        """Read whatever is still coming until ``quiet`` s pass without a frame."""
        while True:
            try:
                await asyncio.wait_for(self.r.ws.recv(), quiet)
            except (TimeoutError, asyncio.TimeoutError):
                return

    async def warm_up(self, tries: int = 60, wait: float = 0.5) -> int:
        """Repeat a small message until its echo comes (the node may subscribe a moment after the
        interfaces are up); bounded. Returns the tries it took."""
        for i in range(1, tries + 1):
            if math.isfinite(await self.roundtrip(self.prepare(3), 3, wait)):
                await self.drain()
                return i
        raise RuntimeError(f"{self.kind}: no echo after {tries} tries ({tries * wait:.0f} s)")


async def measure_rce(master_url: str, paths: list[str], sizes: list[int], reps: int, prog,
                      gap: float = 0.0) -> dict:
    """{path: {size: [ms, ...]}} for the rce paths, on one engine, one robot connection per path;
    each timed round trip after ``gap`` s of silence (none if 0)."""
    out: dict = {}
    robots = []
    try:
        ready = {}
        for kind in paths:
            r = RawRobot(master_url, f"rtt{kind.capitalize()}")
            await r.__aenter__()
            robots.append(r)
            if kind == "c2c":
                req, resp = await setup_c2c(r, "rttC2c")
            else:
                req, resp = await setup_echo(r, f"rtt{kind.capitalize()}C", kind.capitalize())
            p = Path_(r, kind, req, resp)
            p.tries = await p.warm_up()
            ready[kind] = p
        # per size, one block of back-to-back repetitions per path (the paths take turns size by
        # size, so they see similar machine load; within a block the processes stay hot, as in the
        # anchors' loops), each block after one unmeasured round trip of that size
        task = prog.add_task("rce " + ", ".join(paths), total=len(paths) * sum(reps_for(s, reps) for s in sizes))
        for kind in paths:
            out[kind] = {}
        for size in sizes:
            timeout = 10.0 if size < 1_000_000 else 60.0
            for kind in paths:
                p = ready[kind]
                if not math.isfinite(await p.roundtrip(p.prepare(size), size, timeout)):
                    await p.drain()
                samples = out[kind][size] = []
                for _ in range(reps_for(size, reps)):
                    frames = p.prepare(size)
                    if gap > 0:
                        await asyncio.sleep(gap)
                    ms = await p.roundtrip(frames, size, timeout)
                    if not math.isfinite(ms):
                        await p.drain()
                    samples.append(ms)
                    prog.advance(task)
            prog.update(task, description=f"rce {fmt_size(size)}: " + ", ".join(
                f"{k} {fmt_ms(median(out[k][size]))}" for k in paths) + " ms")
    finally:
        for r in robots:
            try:
                await r.__aexit__(None, None, None)
            except Exception:
                pass
    return out


# -- peers with a gap ---------------------------------------------------------------------------

async def ws_floor(sizes: list[int], reps: int, gap: float) -> dict:
    """shared/anchors/ws_rtt.py's raw websockets echo of the JSON DM (server and client in this
    process, as there), each timed round trip after ``gap`` s of silence, one unmeasured round
    trip per size first. Returns ``{"peer", "gap_s", "rtt_ms": {size: median ms}}``."""
    import websockets

    from relay_floor import measure_ws

    async def echo(ws):
        async for m in ws:
            await ws.send(m)
    async with websockets.serve(echo, "127.0.0.1", 0, max_size=None, compression=None) as srv:
        out = await measure_ws(srv.sockets[0].getsockname()[1], sizes, reps, gap)
    return {"peer": "raw-websockets-json", "gap_s": gap, "rtt_ms": out}


ROS1_PEER_TIMEOUT_S = 3600      # s: bound on one bench/ros1_peer.py run (17 sizes x 20 reps x 1 s gap ~ 6 min)


def relay_floor(sizes: list[int], reps: int, gap: float) -> dict:
    """bench/relay_floor.py (client -> relay -> echo -> relay -> client, three processes: the
    floor of any engine with a process between robot and node) with ``gap`` s of silence
    before each round trip; returns its ``{"peer", "gap_s", "rtt_ms": {size: ms}}``."""
    r = subprocess.run([VENV_PY, str(BENCH / "relay_floor.py"), "--gap", str(gap), "--reps", str(reps),
                        "--sizes", ",".join(map(str, sizes))], capture_output=True, text=True,
                       timeout=ROS1_PEER_TIMEOUT_S, cwd=tempfile.gettempdir())
    return peer_result(r, "relay_floor.py")


def ros1_peer(sizes: list[int], reps: int, gap: float) -> dict:
    """bench/ros1_peer.py (rospy, the anchor's topology) with ``gap`` s of silence before each
    round trip; returns its ``{"peer", "gap_s", "rtt_ms": {size: ms}}`` (NaN where none)."""
    env = dict(os.environ, ROS1_PORT=str(free_port()), ROS_HOME=tempfile.mkdtemp(prefix="ros1peer-"))
    r = subprocess.run([SYS_PY, str(BENCH / "ros1_peer.py"), "--gap", str(gap), "--reps", str(reps),
                        "--sizes", ",".join(map(str, sizes))], env=env, capture_output=True, text=True,
                       timeout=ROS1_PEER_TIMEOUT_S, cwd=tempfile.gettempdir())
    return peer_result(r, "ros1_peer.py")


# -- main ------------------------------------------------------------------------------------------

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_ws_impl_argument(p)
    p.add_argument("--sizes", help="comma-separated subset of sizes in bytes (default: shared/anchors/sizes.py)")
    p.add_argument("--reps", type=int, default=int(os.environ.get("REPS", "20")),
                   help="repetitions per size (default: $REPS or 20; a quarter, >= 3, from 1 MB)")
    p.add_argument("--paths", default=",".join(PATHS), help=f"rce paths to measure (default {','.join(PATHS)})")
    p.add_argument("--no-ros1", action="store_true", help="skip the ROS 1 peer (no apt-get)")
    p.add_argument("--no-ws", action="store_true", help="skip the raw websockets floor")
    p.add_argument("--no-relay", action="store_true", help="skip the relay floor (bench/relay_floor.py)")
    p.add_argument("--rounds", type=int, default=1, metavar="K",
                   help="repeat the whole measurement (peers and rce) K times and keep, per series and size, "
                        "the best (lowest) of the K values: for a shared machine whose load comes and goes")
    p.add_argument("--nice", type=int, default=None, metavar="N",
                   help="run the bench and all it starts at niceness N (e.g. -10 as root on a shared machine)")
    p.add_argument("--wait-quiet", type=float, default=0.0, metavar="S",
                   help="first wait up to S s for other processes to use < 0.3 cores (shared machines)")
    p.add_argument("--gap", type=float, default=None, metavar="S",
                   help="S s of silence before every timed round trip (sparse messages); peers: "
                        "bench/ros1_peer.py and the ws floor in this process, with the same gap")
    p.add_argument("--json", type=Path, default=None,
                   help="JSON results (default bench/results/rtt.json, rtt_gap<S>.json with --gap)")
    p.add_argument("--plot", type=Path, default=None,
                   help="PNG plot (default bench/results/rtt.png, rtt_gap<S>.png with --gap)")
    a = p.parse_args(argv)
    stem = "rtt" if a.gap is None else f"rtt_gap{a.gap:g}"
    a.json = a.json or RESULTS / f"{stem}.json"
    a.plot = a.plot or RESULTS / f"{stem}.png"
    return a


def run_round(con, args, sizes: list[int], paths: list[str], ros1_ok: bool) -> dict:
    """One complete measurement: the peers first (no engine running yet), then the rce paths on a
    fresh engine. Returns {"peers": {name: anchor result}, "samples": {path: {size: [ms]}}, "load": ...}."""
    if args.gap is not None:
        return run_gap_round(con, args, sizes, paths, ros1_ok)
    peers, load = {}, {}
    if not args.no_ws:
        with con.status("raw websockets floor (shared/anchors/ws_rtt.py) ..."):
            fl = ForeignLoad().start()
            peers["ws_floor"] = run_anchor("ws_rtt.py", VENV_PY, args.reps)
            load["ws_floor"] = fl.stop()
        con.print(f"ws floor done ({peers['ws_floor']['peer']})")
    if not args.no_relay:
        with con.status("relay floor (bench/relay_floor.py: client -> relay -> echo, three processes) ..."):
            fl = ForeignLoad().start()
            peers["relay_floor"] = relay_floor(sizes, args.reps, 0.0)
            load["relay_floor"] = fl.stop()
        con.print("relay floor done")
    if ros1_ok:
        with con.status("ROS 1 single master (shared/anchors/ros1_rtt.py) ..."):
            fl = ForeignLoad().start()
            peers["ros1"] = run_anchor("ros1_rtt.py", SYS_PY, args.reps,
                                       env={"ROS1_PORT": str(free_port()),
                                            "ROS_HOME": tempfile.mkdtemp(prefix="ros1rtt-")})
            load["ros1"] = fl.stop()
        con.print(f"ROS 1 done ({peers['ros1']['peer']})")
    with engine(robot_args=("--ws-impl", args.ws_impl)) as eng, progress(con) as prog:
        fl = ForeignLoad().start()
        samples = asyncio.run(measure_rce(eng.master_url, paths, sizes, args.reps, prog))
        load["rce"] = fl.stop()
    return {"peers": peers, "samples": samples, "load": load}


def run_gap_round(con, args, sizes: list[int], paths: list[str], ros1_ok: bool) -> dict:
    """:func:`run_round` with ``args.gap`` s of silence before every timed round trip, for the
    peers (bench/ros1_peer.py, :func:`ws_floor`) and the rce paths alike."""
    peers, load, gap = {}, {}, args.gap
    if not args.no_ws:
        with con.status(f"raw websockets floor, gap {gap:g} s ..."):
            fl = ForeignLoad().start()
            peers["ws_floor"] = asyncio.run(ws_floor(sizes, args.reps, gap))
            load["ws_floor"] = fl.stop()
        con.print(f"ws floor done ({peers['ws_floor']['peer']}, gap {gap:g} s)")
    if not args.no_relay:
        with con.status(f"relay floor (bench/relay_floor.py), gap {gap:g} s ..."):
            fl = ForeignLoad().start()
            peers["relay_floor"] = relay_floor(sizes, args.reps, gap)
            load["relay_floor"] = fl.stop()
        con.print(f"relay floor done (gap {gap:g} s)")
    if ros1_ok:
        with con.status(f"ROS 1 (bench/ros1_peer.py), gap {gap:g} s ..."):
            fl = ForeignLoad().start()
            peers["ros1"] = ros1_peer(sizes, args.reps, gap)
            load["ros1"] = fl.stop()
        con.print(f"ROS 1 done ({peers['ros1']['peer']}, gap {gap:g} s)")
    with engine(robot_args=("--ws-impl", args.ws_impl)) as eng, progress(con) as prog:
        fl = ForeignLoad().start()
        samples = asyncio.run(measure_rce(eng.master_url, paths, sizes, args.reps, prog, gap))
        load["rce"] = fl.stop()
    return {"peers": peers, "samples": samples, "load": load}


def main(argv=None) -> int:
    args = parse_args(argv)
    con = console()
    all_sizes = anchor_sizes()
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else all_sizes
    paths = [p for p in args.paths.split(",") if p]
    bad = [p for p in paths if p not in PATHS]
    if bad:
        con.print(f"[red]unknown path(s) {bad}; known: {PATHS}")
        return 2
    notes = []
    if any(s not in all_sizes for s in sizes):
        notes.append("sizes not in shared/anchors/sizes.py have no peer values")

    set_nice(args.nice, log=con.print)
    wait_quiet(args.wait_quiet, log=con.print)
    ros1_ok = False
    if not args.no_ros1:
        ros1_ok, why = ensure_ros1(log=con.print)
        if not ros1_ok:
            notes.append(f"ROS 1 skipped: {why}")
            con.print(f"[yellow]ROS 1 skipped: {why}")
    rounds = []
    for k in range(args.rounds):
        if args.rounds > 1:
            con.rule(f"round {k + 1} of {args.rounds}")
        rounds.append(run_round(con, args, sizes, paths, ros1_ok))
    load = [rd["load"] for rd in rounds]
    busy = {f"{name}{'' if args.rounds == 1 else f' (round {k + 1})'}": v["other_cores"]
            for k, ld in enumerate(load) for name, v in ld.items() if v["other_cores"] > 0.25}
    if busy:
        notes.append(f"other work on the machine while measuring (cores busy with processes not of this bench): "
                     f"{busy}; absolute times and ratios are perturbed")

    res = {"sizes": sizes, "reps": args.reps, "gap_s": args.gap,
           "reps_by_size": [reps_for(s, args.reps) for s in sizes], "rounds": args.rounds,
           "paths": {"rce_converter": "robot -> SubscriberConverter (JSON) -> Test/stringEcho -> PublisherConverter "
                                     "-> robot",
                     "rce_forwarder": "robot -> SubscriberForwarder (msg* binary) -> Test/stringEcho -> "
                                      "PublisherForwarder -> robot",
                     "rce_c2c": "robot -> forwarder -> container A /relay -> interface link -> container B "
                                "stringEcho -> forwarder -> robot",
                     "ros1_ms": "shared/anchors/ros1_rtt.py (rospy, single master, TCPROS; medians only)",
                     "ws_floor_ms": "shared/anchors/ws_rtt.py (raw websockets + JSON DM echo; medians only)",
                     "relay_floor_ms": "bench/relay_floor.py (client -> relay -> echo -> relay -> client, three "
                                       "processes, raw websockets on uvloop; medians only)"}}
    if args.gap is not None:
        res["paths"]["ros1_ms"] = f"bench/ros1_peer.py --gap {args.gap:g} (the ROS 1 anchor's topology and message)"
        res["paths"]["ws_floor_ms"] = f"ws_rtt.py's echo in the bench process, gap {args.gap:g} s"
    best = (lambda xs: min((x for x in xs if math.isfinite(x)), default=float("nan")))  # noqa: E731
    per_round: dict = {}
    for kind in PATHS:
        key = f"rce_{kind}"
        if kind not in paths:
            for suffix in ("_ms", "_p90_ms", "_p10_ms", "_lost"):
                res[key + suffix] = None
            continue
        for stat, fn in (("_ms", median), ("_p90_ms", lambda v: percentile(v, 90)),
                         ("_p10_ms", lambda v: percentile(v, 10))):
            per = [[fn(rd["samples"][kind][z]) for z in sizes] for rd in rounds]
            res[key + stat] = [best(col) for col in zip(*per, strict=True)]
            if stat == "_ms":
                per_round[key + stat] = per
        res[f"{key}_lost"] = [sum(sum(1 for x in rd["samples"][kind][z] if not math.isfinite(x)) for rd in rounds)
                              for z in sizes]
    for peer, key in (("ros1", "ros1_ms"), ("ws_floor", "ws_floor_ms"), ("relay_floor", "relay_floor_ms")):
        if peer not in rounds[0]["peers"]:
            res[key] = None
            continue
        per = [[rd["peers"][peer]["rtt_ms"].get(z, float("nan")) for z in sizes] for rd in rounds]
        res[key] = [best(col) for col in zip(*per, strict=True)]
        per_round[key] = per
    if args.rounds > 1:
        res["per_round"] = per_round
    small = [i for i, z in enumerate(sizes) if z <= 1623]
    large = [i for i, z in enumerate(sizes) if z >= 1_000_000]

    def gm(a, b, idx):
        if not res.get(a) or not res.get(b) or not idx:
            return None
        return geomean(ratio(res[a][i], res[b][i]) for i in idx)
    res["summary"] = {
        "converter_over_ros1_small_geomean": gm("rce_converter_ms", "ros1_ms", small),
        "forwarder_over_ros1_large_geomean": gm("rce_forwarder_ms", "ros1_ms", large),
        "converter_over_ws_small_geomean": gm("rce_converter_ms", "ws_floor_ms", small),
        "forwarder_over_ws_large_geomean": gm("rce_forwarder_ms", "ws_floor_ms", large),
        "relay_floor_over_ros1_small_geomean": gm("relay_floor_ms", "ros1_ms", small),
        "converter_over_relay_floor_small_geomean": gm("rce_converter_ms", "relay_floor_ms", small),
        "forwarder_over_relay_floor_small_geomean": gm("rce_forwarder_ms", "relay_floor_ms", small),
        "small": "sizes <= 1623 B", "large": "sizes >= 1 MB"}
    res["machine_load"] = load if args.rounds > 1 else load[0]
    res["nice"], res["ws_impl"] = args.nice, args.ws_impl
    res["notes"] = notes
    write_json(args.json, res)
    print_table(con, res)
    plot(res, args.plot)
    con.print(f"results: {args.json}  plot: {args.plot}")
    return 0


def print_table(con, res: dict) -> None:
    from rich.table import Table
    t = Table(title="round trip, ms (median / p90 for rce; medians for peers)"
                    + ("" if res.get("gap_s") is None else f"; {res['gap_s']:g} s silence before each")
                    + (f"; each value the lowest of {res['rounds']} rounds" if res.get("rounds", 1) > 1 else ""))
    for c in ("size", "conv", "conv p90", "fwd", "fwd p90", "c2c", "c2c p90", "ros1", "ws", "relay",
              "conv/ros1", "fwd/ros1", "c2c/ros1", "conv/ws", "fwd/ws", "conv/relay"):
        t.add_column(c, justify="right")
    g = lambda k, i: (res.get(k) or [float("nan")] * len(res["sizes"]))[i]  # noqa: E731
    for i, z in enumerate(res["sizes"]):
        t.add_row(fmt_size(z), fmt_ms(g("rce_converter_ms", i)), fmt_ms(g("rce_converter_p90_ms", i)),
                  fmt_ms(g("rce_forwarder_ms", i)), fmt_ms(g("rce_forwarder_p90_ms", i)),
                  fmt_ms(g("rce_c2c_ms", i)), fmt_ms(g("rce_c2c_p90_ms", i)),
                  fmt_ms(g("ros1_ms", i)), fmt_ms(g("ws_floor_ms", i)), fmt_ms(g("relay_floor_ms", i)),
                  fmt_ratio(ratio(g("rce_converter_ms", i), g("ros1_ms", i))),
                  fmt_ratio(ratio(g("rce_forwarder_ms", i), g("ros1_ms", i))),
                  fmt_ratio(ratio(g("rce_c2c_ms", i), g("ros1_ms", i))),
                  fmt_ratio(ratio(g("rce_converter_ms", i), g("ws_floor_ms", i))),
                  fmt_ratio(ratio(g("rce_forwarder_ms", i), g("ws_floor_ms", i))),
                  fmt_ratio(ratio(g("rce_converter_ms", i), g("relay_floor_ms", i))))
    con.print(t)
    s = res["summary"]
    con.print("geometric mean ratios: "
              f"converter/ros1 at <= 1.6 kB = {fmt_ratio(s['converter_over_ros1_small_geomean'])}, "
              f"forwarder/ros1 at >= 1 MB = {fmt_ratio(s['forwarder_over_ros1_large_geomean'])}, "
              f"converter/ws at <= 1.6 kB = {fmt_ratio(s['converter_over_ws_small_geomean'])}, "
              f"forwarder/ws at >= 1 MB = {fmt_ratio(s['forwarder_over_ws_large_geomean'])}, "
              f"relay floor/ros1 at <= 1.6 kB = {fmt_ratio(s['relay_floor_over_ros1_small_geomean'])}, "
              f"converter/relay floor at <= 1.6 kB = {fmt_ratio(s['converter_over_relay_floor_small_geomean'])}")
    for n in res["notes"]:
        con.print(f"[yellow]note: {n}")


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 5.5))
    series = [("rce_converter", "rce converter (JSON)", "o-"), ("rce_forwarder", "rce forwarder (binary)", "s-"),
              ("rce_c2c", "rce container->container (fwd)", "^-"),
              ("ros1", "ROS 1 rospy (" + ("anchor)" if res.get("gap_s") is None else "bench/ros1_peer.py)"), "x--"),
              ("ws_floor", "raw websockets + JSON (floor)", "+:"),
              ("relay_floor", "relay floor: client -> relay -> echo (3 processes)", "d:")]
    for key, label, style in series:
        ys = res.get(f"{key}_ms")
        if not ys:
            continue
        pts = [(x, y) for x, y in zip(res["sizes"], ys, strict=False) if y is not None and math.isfinite(y) and y > 0]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=label, markersize=4)
        p90 = res.get(f"{key}_p90_ms")
        if p90:
            q = [(x, y) for x, y in zip(res["sizes"], p90, strict=False)
                 if y is not None and math.isfinite(y) and y > 0]
            if q:
                ax.plot(*zip(*q, strict=True), style[0] + ":", alpha=0.35, color=ax.lines[-1].get_color(), markersize=2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("payload size, bytes")
    ax.set_ylabel("round trip, ms (median; faint: rce p90)")
    gap = res.get("gap_s")
    ax.set_title("RTT robot -> container echo -> robot, loopback"
                 + ("" if gap is None else f", {gap:g} s of silence before each"))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
