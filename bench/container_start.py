"""Container start time and per-container memory overhead, per sandbox kind.

Start time: from the robot sending CC (then CN addNodes, back to back) to

- ``started``: the robot has an ST ``node started`` for every node (the processes run), and
- ``ready``: every node has registered on its container's bus (polled through the admin API
  ``/bus`` every 5 ms) -- "all nodes running";

median (and p10/p90/min/max) over ``--reps`` containers created one after the other, each
destroyed (DC) before the next, after one unmeasured warm-up. The container host keeps one
warm spare environment (its default); each repetition waits until the previous container's
environment process has exited (a DC's teardown would otherwise still hold the robot's next
request) and the spare is back, so every CC finds the host in the same state. ``forked``:
how many of the nodes the container's zygote forked (the rest were exec'd).

Sandbox alone: in this process, a sandbox's setup (cgroup, namespaces, init ready), one
spawn of ``/bin/true`` to its exit, and close -- what the sandbox itself costs, without the
engine and the nodes' Python start.

Memory: with the container and its nodes running, resident (RSS) and unique (USS) memory of
the environment process, of the sandbox's own processes (``unshare`` + the container's init +
one waiting ``nsenter`` per exec'd node; nothing for ``unconfined``), of the container's
zygote (:mod:`rce_container.zygote`) and of the nodes.

Usage::

    .venv/bin/python bench/container_start.py [--reps 20] [--nodes 2] [--sandbox both|namespaced|unconfined]

Prints a table and writes ``bench/results/container_start.json``. ``namespaced`` needs root.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import time
import urllib.request
from pathlib import Path

import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, engine, median, percentile, write_json  # noqa: E402
from wsclient import RawRobot  # noqa: E402

PLUMBING = ("unshare", "nsenter", "sh")
ZYGOTE = "rce_container.zygote"     # in the zygote's command line
SETTLE_TIMEOUT = 30.0               # s for a destroyed container's environment to exit


def spares(metrics_port: int) -> int:
    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as r:
        for line in r.read().decode().splitlines():
            if line.startswith("rce_container_host_spares "):
                return int(float(line.split()[1]))
    return 0


async def wait_spare(metrics_port: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while await asyncio.to_thread(spares, metrics_port) < 1:
        if time.monotonic() > deadline:
            raise TimeoutError("the container host did not restart its warm spare environment")
        await asyncio.sleep(0.02)


def mem(pids) -> tuple[float, float]:
    """(RSS, USS) in MiB summed over ``pids``."""
    rss = uss = 0
    for p in pids:
        try:
            info = psutil.Process(p).memory_full_info()
            rss, uss = rss + info.rss, uss + info.uss
        except psutil.NoSuchProcess:
            pass
    return rss / 2**20, uss / 2**20


def memory_footprint(eng, ctag: str) -> dict:
    s = eng.admin(f"/api/containers/testUser/{ctag}/stats")
    env_pid = s["environment"]["pid"]
    info = s["sandbox_info"]
    if "cgroup" in info:
        pids = [int(p) for p in Path(info["cgroup"]["dirs"][0], "cgroup.procs").read_text().split()]
    else:
        pids = [p for n in s["per_node"].values() if n["pid"]
                for p in [n["pid"], *(c.pid for c in psutil.Process(n["pid"]).children(recursive=True))]]
    if s["per_node"] and "cgroup" not in info:      # unconfined: the zygote is the nodes' parent
        pids += list({psutil.Process(p).ppid() for p in pids} - set(pids) - {env_pid})
    plumbing, zygote, nodes = [], [], []
    for p in pids:
        try:
            proc = psutil.Process(p)
            name, cmd = proc.name(), " ".join(proc.cmdline())
        except psutil.NoSuchProcess:
            continue
        (zygote if ZYGOTE in cmd else plumbing if name in PLUMBING or "nsinit.py" in cmd else nodes).append(p)
    env_rss, env_uss = mem([env_pid])
    sb_rss, sb_uss = mem(plumbing)
    zy_rss, zy_uss = mem(zygote)
    node_rss, node_uss = mem(nodes)
    return {"environment_rss_mib": env_rss, "environment_uss_mib": env_uss,
            "sandbox_processes": len(plumbing), "sandbox_rss_mib": sb_rss, "sandbox_uss_mib": sb_uss,
            "zygote_rss_mib": zy_rss, "zygote_uss_mib": zy_uss,
            "node_processes": len(nodes), "nodes_rss_mib": node_rss, "nodes_uss_mib": node_uss,
            "overhead_rss_mib": env_rss + sb_rss + zy_rss, "overhead_uss_mib": env_uss + sb_uss + zy_uss}


async def wait_gone(pid: int, timeout: float = SETTLE_TIMEOUT) -> None:
    """Wait until process ``pid`` has exited (polled)."""
    deadline = time.monotonic() + timeout
    while psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
        if time.monotonic() > deadline:
            raise TimeoutError(f"environment {pid} did not exit")
        await asyncio.sleep(0.01)


async def one(eng, r: RawRobot, ctag: str, nodes: int) -> tuple[float, float, dict]:
    names = [f"/n{k}/echo" for k in range(nodes)]
    t0 = time.perf_counter()
    await r.send("CC", {"containerTag": ctag})
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": f"echo{k}", "pkg": "Test", "exe": "stringEcho.py",
                          "name": "echo", "namespace": f"n{k}"} for k in range(nodes)])
    started: set[str] = set()
    while len(started) < nodes:
        d = await r.expect("ST", timeout=60, pred=lambda d: d.get("topic") == "node" and d.get("cTag") == ctag)
        if d["status"] == "started":
            started.add(d["nTag"])
        elif d["status"] == "exited":
            raise RuntimeError(f"node {d['nTag']} exited: {d}")
    t_started = time.perf_counter()
    while True:
        bus = await asyncio.to_thread(eng.admin, f"/api/containers/testUser/{ctag}/bus")
        if all(any(n["name"] == name for n in bus["nodes"]) for name in names):
            break
        if time.perf_counter() - t0 > 60:
            raise TimeoutError(f"nodes of {ctag} never registered: {bus['nodes']}")
        await asyncio.sleep(0.005)
    t_ready = time.perf_counter()
    stats = await asyncio.to_thread(eng.admin, f"/api/containers/testUser/{ctag}/stats")
    return (t_started - t0) * 1000, (t_ready - t0) * 1000, stats


async def run_mode(mode: str, reps: int, nodes: int) -> dict:
    with engine(container_args=("--sandbox", mode, "--metrics-port", "0")) as eng:
        metrics_port = json.loads((eng.workdir / "container0.ready").read_text())["metrics_port"]
        started_ms, ready_ms, forked, footprint = [], [], [], None
        async with RawRobot(eng.master_url, "benchBot") as r:
            for i in range(reps + 1):
                await wait_spare(metrics_port)
                ctag = f"start{i}"
                s, rd, stats = await one(eng, r, ctag, nodes)
                if i == 0:
                    footprint = await asyncio.to_thread(memory_footprint, eng, ctag)   # nodes are up
                else:
                    started_ms.append(s)
                    ready_ms.append(rd)
                    forked.append(stats["nodes"].get("forked", 0))
                print(f"  {mode:<11} rep {i:>2}{' (warm-up)' if i == 0 else ''}: started {s:7.1f} ms, "
                      f"ready {rd:7.1f} ms, forked {stats['nodes'].get('forked', 0)}/{nodes}", flush=True)
                await r.send("DC", {"containerTag": ctag})
                deadline = time.monotonic() + 30
                while await asyncio.to_thread(eng.admin, "/api/containers"):
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"{ctag} was not destroyed")
                    await asyncio.sleep(0.01)
                await wait_gone(stats["environment"]["pid"])

    def summary(xs):
        return {"median": median(xs), "p10": percentile(xs, 10), "p90": percentile(xs, 90), "min": min(xs),
                "max": max(xs), "samples": [round(x, 2) for x in xs]}
    return {"started_ms": summary(started_ms), "ready_ms": summary(ready_ms), "forked": sum(forked),
            "nodes_started": len(forked) * nodes, "memory": footprint}


async def sandbox_micro(mode: str, reps: int) -> dict:
    """In this process, without the engine: a sandbox's ``setup`` (cgroup + namespaces + init
    ready), one ``spawn`` of ``/bin/true`` to its exit, and ``close`` (ms, median of ``reps``)."""
    import tempfile
    from rce_container import sandbox as sandboxes
    cls = sandboxes.select(mode)
    scope = sandboxes.host_scope("bench-micro")
    root = Path(tempfile.mkdtemp(prefix="rce-micro-"))
    setup, spawn, close = [], [], []
    try:
        cls.prepare_host(scope)
        for i in range(reps + 1):
            wd = root / f"c{i}"
            wd.mkdir()
            sb = cls(10_000 + i, "micro", {"cpu": 1, "memory": 256, "size": 100}, wd, bus_socket=wd / "bus.sock",
                     scope=scope, grace=1)
            t0 = time.perf_counter()
            await sb.setup()
            t1 = time.perf_counter()
            proc = await sb.spawn(["/bin/true"], dict(os.environ))
            await proc.wait()
            await sb.kill(proc)
            t2 = time.perf_counter()
            await sb.close()
            t3 = time.perf_counter()
            if i:
                setup.append((t1 - t0) * 1000)
                spawn.append((t2 - t1) * 1000)
                close.append((t3 - t2) * 1000)
    finally:
        cls.cleanup_host(scope)
        import shutil
        shutil.rmtree(root, ignore_errors=True)
    return {"setup_ms": median(setup), "spawn_true_ms": median(spawn), "close_ms": median(close),
            "setup_p90_ms": percentile(setup, 90)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reps", type=int, default=20, help="measured containers per sandbox kind (default 20)")
    p.add_argument("--nodes", type=int, default=2, help="stringEcho nodes per container (default 2)")
    p.add_argument("--sandbox", default="both", choices=["both", "namespaced", "unconfined"])
    p.add_argument("--out", type=Path, default=RESULTS / "container_start.json")
    a = p.parse_args(argv)
    modes = ["namespaced", "unconfined"] if a.sandbox == "both" else [a.sandbox]
    if "namespaced" in modes and os.geteuid() != 0:
        if a.sandbox == "namespaced":
            print("container_start: the namespaced sandbox needs root", file=sys.stderr)
            return 2
        print("container_start: not root, measuring the unconfined sandbox only", file=sys.stderr)
        modes.remove("namespaced")
    results = {}
    for mode in modes:
        print(f"== {mode}: sandbox setup/spawn/close, {a.reps} times", flush=True)
        micro = asyncio.run(sandbox_micro(mode, a.reps))
        print(f"== {mode}: {a.reps} containers of {a.nodes} nodes", flush=True)
        results[mode] = asyncio.run(run_mode(mode, a.reps, a.nodes))
        results[mode]["sandbox"] = micro
    load = os.getloadavg()
    print(f"\ncontainer start, CC -> all nodes running ({a.nodes} stringEcho nodes, median of {a.reps}; "
          f"load average {load[0]:.1f} on {os.cpu_count()} CPUs)")
    print(f"{'sandbox':<12}{'started ms':>12}{'ready ms':>10}{'p10':>8}{'p90':>8}{'forked':>9}"
          f"{'env RSS':>10}{'sandbox RSS':>13}{'zygote RSS':>12}{'overhead RSS':>14}{'overhead USS':>14}")
    for mode, r in results.items():
        m = r["memory"]
        print(f"{mode:<12}{r['started_ms']['median']:>12.1f}{r['ready_ms']['median']:>10.1f}"
              f"{r['ready_ms']['p10']:>8.1f}{r['ready_ms']['p90']:>8.1f}{r['forked']:>5}/{r['nodes_started']:<3}"
              f"{m['environment_rss_mib']:>9.1f}M{m['sandbox_rss_mib']:>12.1f}M{m.get('zygote_rss_mib', 0):>11.1f}M"
              f"{m['overhead_rss_mib']:>13.1f}M{m['overhead_uss_mib']:>13.1f}M")
    print(f"\nsandbox alone (in-process, median of {a.reps})")
    print(f"{'sandbox':<12}{'setup ms':>10}{'setup p90':>11}{'spawn /bin/true ms':>20}{'close ms':>10}")
    for mode, r in results.items():
        sb = r["sandbox"]
        print(f"{mode:<12}{sb['setup_ms']:>10.1f}{sb['setup_p90_ms']:>11.1f}{sb['spawn_true_ms']:>20.1f}"
              f"{sb['close_ms']:>10.1f}")
    write_json(a.out, {"reps": a.reps, "nodes": a.nodes, "host": platform.node(), "cpus": os.cpu_count(),
                       "loadavg": load, "kernel": platform.release(), "python": platform.python_version(),
                       "results": results})
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
