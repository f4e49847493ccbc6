"""CPU per round trip, per process: where a converter (or forwarder) round trip spends its CPU.

Runs the engine (:mod:`common`'s ``engine``) with one container of ``Test/stringEcho.py`` and
the robot-side interfaces of :mod:`rtt` (``setup_echo``), then ``--n`` back-to-back round trips
of ``--size`` bytes, and reads each process's CPU time (psutil, user + system) before and after:
rce-robot, the environment, the echo node, the master, the container host and this process (the
robot's client). ``--direct both`` runs it twice, with direct links off (``RCE_DIRECT_LINKS=0``:
every message through the environment) and on, so the two lines compare in one run.

Usage::

    .venv/bin/python bench/rtt_cpu.py [--n 3000] [--size 3] [--kind converter|forwarder]
        [--direct both|on|off] [--json PATH]

With direct links on, the round trips start once the node's direct routes are up (the
environment's ``direct`` stats). ``environment_plane_msgs`` in the JSON counts the messages the
environment's data plane carried during the round trips: two per round trip through it, none
direct.

Results: a table (us of CPU per round trip per process, and the median round trip) and
``bench/results/rtt_cpu.json``.
"""
from __future__ import annotations

import argparse
import asyncio
import time
from pathlib import Path

import psutil

from common import (RESULTS, Engine, RawRobot, add_ws_impl_argument, console, engine, median, process_cpu_s,
                    write_json)
from rtt import Path_, setup_echo

ROLES = (("robot", ("rce-robot",)), ("environment", ("rce_container.environment",)), ("node", ("stringEcho",)),
         ("master", ("rce-master",)), ("container host", ("rce-container",)))


def processes(roots: list[int], workdir: str) -> dict[str, list[psutil.Process]]:
    """The engine's processes by role (the first command-line marker that matches), and this
    client: ``roots`` (the pids it started) and their descendants, and the nodes, whose zygote is
    no one's child (found by their working directory, a container's, under ``workdir``)."""
    out: dict[str, list[psutil.Process]] = {role: [] for role, _ in ROLES}
    tree = []
    for pid in roots:
        try:
            root = psutil.Process(pid)
            tree += [root, *root.children(recursive=True)]
        except psutil.Error:
            pass
    for p in psutil.process_iter():
        try:
            if p not in tree and p.cwd().startswith(workdir):
                tree.append(p)
        except psutil.Error:
            pass
    for p in tree:
        try:
            cmd = " ".join(p.cmdline())
        except psutil.Error:
            continue
        for role, marks in ROLES:
            if any(m in cmd for m in marks):
                out[role].append(p)
                break
    out["client"] = [psutil.Process()]
    return out


def cpu_seconds(procs: dict[str, list[psutil.Process]]) -> dict[str, float]:
    out = {}
    for role, ps in procs.items():
        total = 0.0
        for p in ps:
            try:
                total += process_cpu_s(p)
            except psutil.Error:
                pass
        out[role] = total
    return out


ROUTES_WAIT = 60.0      # s the node's direct routes may take to come up (a fresh clone compiles its modules first)


async def environment_stats(eng: Engine, ctag: str) -> dict:
    """Container ``ctag``'s environment counters (``stats``' ``environment``: its data plane, its direct routes)."""
    return (await asyncio.to_thread(eng.admin, f"/api/containers/testUser/{ctag}/stats"))["environment"]


def plane_msgs(env: dict) -> int:
    """Messages the environment's data plane has taken in and sent out."""
    return env["dataplane"]["msgs_in"] + env["dataplane"]["msgs_out"]


async def direct_routes(eng: Engine, ctag: str) -> dict:
    """Wait until container ``ctag``'s node has its direct links (``environment.direct``: a claim
    of the robot's interface and a publisher route); returns those stats. Raises RuntimeError
    after :data:`ROUTES_WAIT` s."""
    deadline = time.monotonic() + ROUTES_WAIT
    while True:
        d = (await environment_stats(eng, ctag))["direct"]
        if d.get("claims", 0) >= 1 and d.get("routes", 0) >= 1:
            return d
        if time.monotonic() > deadline:
            raise RuntimeError(f"no direct routes after {ROUTES_WAIT:g} s: {d}")
        await asyncio.sleep(0.1)


async def measure(eng: Engine, direct: bool, kind: str, n: int, size: int) -> dict:
    """``{median_ms, us_per_rt: {role: us}}`` over ``n`` round trips of ``size`` bytes, on engine
    ``eng`` (``direct``: wait for the node's direct links first)."""
    async with RawRobot(eng.master_url, "cpuR") as r:
        req, resp = await setup_echo(r, "cpuC", "Converter" if kind == "converter" else "Forwarder")
        path = Path_(r, kind, req, resp)
        await path.warm_up()
        if direct:
            await direct_routes(eng, "cpuC")
        frames = path.prepare(size)
        for _ in range(200):                    # every process is hot
            await path.roundtrip(frames, size, 2.0)
        procs = processes([q.pid for q in eng.procs], str(eng.workdir))
        m0 = plane_msgs(await environment_stats(eng, "cpuC"))
        c0 = cpu_seconds(procs)
        samples = [await path.roundtrip(frames, size, 2.0) for _ in range(n)]
        c1 = cpu_seconds(procs)
        m1 = plane_msgs(await environment_stats(eng, "cpuC"))
    return {"median_ms": round(median(samples), 4),
            "us_per_rt": {k: round((c1[k] - c0[k]) / n * 1e6, 1) for k in c0},
            "environment_plane_msgs": m1 - m0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="CPU per round trip, per process (see the module doc).")
    p.add_argument("--n", type=int, default=3000, help="round trips per setting (default 3000)")
    p.add_argument("--size", type=int, default=3, help="payload bytes (default 3)")
    p.add_argument("--kind", choices=("converter", "forwarder"), default="converter")
    p.add_argument("--direct", choices=("both", "on", "off"), default="both")
    p.add_argument("--json", default=str(RESULTS / "rtt_cpu.json"))
    add_ws_impl_argument(p)
    a = p.parse_args(argv)
    con = console()
    settings = {"both": ("off", "on"), "on": ("on",), "off": ("off",)}[a.direct]
    res = {"kind": a.kind, "size": a.size, "n": a.n, "ws_impl": a.ws_impl, "runs": {}}
    for s in settings:
        t0 = time.monotonic()
        with engine(env={"RCE_DIRECT_LINKS": "1" if s == "on" else "0"}, robot_args=("--ws-impl", a.ws_impl)) as eng:
            res["runs"][f"direct_{s}"] = r = asyncio.run(measure(eng, s == "on", a.kind, a.n, a.size))
        con.print(f"direct links {s:3s}: median {r['median_ms']:.3f} ms; CPU us per round trip: "
                  + ", ".join(f"{k} {v:.0f}" for k, v in r["us_per_rt"].items())
                  + f"  ({time.monotonic() - t0:.0f} s)")
    write_json(Path(a.json), res)
    con.print(f"results: {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
