"""A follower out of coverage riding on relays (docs/relays.md), in network namespaces this bench makes
(root; deleted afterwards, also on failure; rce/tools/netlab.py):

- the cloud (the real engine) in the root namespace; leaders L1 and L2 (``rce-ros --relay-port``) with
  uplinks to it; a follower F (``rce-ros --relays L1,L2``) with links only to L1 and L2, and a direct
  link to the cloud that is down until t = 60 s;
- F's bus carries a 10 Hz state stream (robot -> container cF's stringEcho.py -> robot, converters in
  lane ``state``: while no path exists each side keeps only its newest), and the cloud sends a 1 Hz
  command stream into container cK (admin API) that reaches F through converters in lane ``control``;
- t = 20 s: the F-L1 link goes dark (L1's end down: F's packets vanish without an error);
  t = 40 s: F's link to L2 goes dark too, and both come back at t = 50 s;
- t = 55 s: F's link to L2 goes dark for good: L1 is F's only way to the cloud; t = 62 s: L1's uplink goes
  down (L1 answers 504: it cannot reach the cloud), and up again at t = 67 s;
- t = 75 s: F's direct link comes up.

It reports, per event: how long F was dark (the gap in echoes, and the part of it after a path existed
again), the age of the first state after it and how long until a state sent after the path returned
arrived; commands and states lost or duplicated; messages dropped or superseded (counted by rce-ros and the cloud);
the relays' CPU per relayed robot (the relaying leader's CPU less the idle leader's, same seconds);
F's path as the master saw it. JSON in bench/results/relay.json and a PNG timeline.

    sudo .venv/bin/python bench/relay.py [--out bench/results/relay.json]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
import time
from pathlib import Path

import psutil

from common import RESULTS, engine, git_head, process_cpu_s, pyplot, write_json

import rce.node
from rce.tools.netlab import NetLab, RelayTopology

RELAY_PORT = 9100
STATE_HZ, COMMAND_HZ = 10.0, 1.0
EVENTS = {"L1 vanishes": 20.0, "partition": 40.0, "links back": 50.0, "L2 gone": 55.0, "L1 uplink cut": 62.0,
          "L1 uplink back": 67.0, "direct link": 75.0}
END = 90.0                    # s of the run after the first echo
DRAIN = 5.0                   # s after the streams stop for the last echoes
POLL = 0.25                   # s between looks at the master's view of F's path and the relays' CPU
HARNESS_QUEUE = 10000         # the bench's own subscriber's queue: large, so that it drops nothing itself
ROBOT_WAIT = 90.0             # s for the robots to log in and their interfaces to come up


def echo_interfaces(ctag: str, robot: str, req: str, resp: str, lane: str) -> list[dict]:
    """Container ``ctag``'s stringEcho.py topics, and robot-side converters ``req`` (F's bus topic ``/req``)
    and ``resp`` (F's bus ``/resp``) in ``lane``."""
    return [{"eTag": ctag, "iTag": "req", "iType": "PublisherInterface", "iCls": "std_msgs/String",
             "addr": "/stringEchoReq"},
            {"eTag": ctag, "iTag": "resp", "iType": "SubscriberInterface", "iCls": "std_msgs/String",
             "addr": "/stringEchoResp"},
            {"eTag": robot, "iTag": req, "iType": "SubscriberConverter", "iCls": "std_msgs/String",
             "addr": f"/{req}", "lane": lane},
            {"eTag": robot, "iTag": resp, "iType": "PublisherConverter", "iCls": "std_msgs/String",
             "addr": "/resp", "lane": lane}]


def robot_config(url: str, robot: str, echo: bool = False, state_lane: str = "state") -> dict:
    """``state_lane``: the state stream's lane (``control``: every state kept while no path exists)."""
    cfg = {"url": url, "userID": "testUser", "password": "testUser", "robotID": robot}
    if echo:
        cfg.update({
            "containers": [{"cTag": "cF"}, {"cTag": "cK"}],
            "nodes": [{"cTag": c, "nTag": "echo", "pkg": "Test", "exe": "stringEcho.py"} for c in ("cF", "cK")],
            "interfaces": (echo_interfaces("cF", robot, "req", "resp", state_lane)
                           + echo_interfaces("cK", robot, "creq", "cresp", "control")),
            "connections": [{"tagA": f"{c}/{t}", "tagB": f"{robot}/{r}"}
                            for c, pairs in (("cF", (("req", "req"), ("resp", "resp"))),
                                             ("cK", (("req", "creq"), ("resp", "cresp"))))
                            for t, r in pairs]})
    return cfg


async def start_robot(lab: NetLab, ns: str, cfg: dict, work: Path,
                      *args: str) -> tuple[asyncio.subprocess.Process, Path]:
    """rce-ros in namespace ``ns``, its output in ``work/ROBOT.log``; returns it and its bus socket."""
    path = work / f"{cfg['robotID']}.config"
    path.write_text(json.dumps(cfg))
    bus = work / f"{cfg['robotID']}.sock"
    out = open(work / f"{cfg['robotID']}.log", "wb")
    proc = await asyncio.create_subprocess_exec(
        *lab.wrap(ns, [sys.executable, "-m", "rce_client.rce_ros", str(path), "--bus", str(bus), *args]),
        stdout=out, stderr=asyncio.subprocess.STDOUT)
    return proc, bus


async def wait_text(log: Path, text: str, proc) -> None:
    async with asyncio.timeout(ROBOT_WAIT):
        while text not in (log.read_text(errors="replace") if log.exists() else ""):
            if proc.returncode is not None:
                raise RuntimeError(f"{log.name}: rce-ros exited:\n{log.read_text(errors='replace')[-3000:]}")
            await asyncio.sleep(0.1)        # polling a log file: the process tells nothing else


class Recorder:
    """What F's bus gets back on /resp: (arrival, kind "s"/"c", number, send time)."""

    def __init__(self):
        self.got: list[tuple[float, str, int, float]] = []
        self.first = asyncio.Event()

    def __call__(self, msg) -> None:
        kind, n, sent = msg.data.split(":")
        self.got.append((time.monotonic(), kind, int(n), float(sent)))
        if kind == "s":
            self.first.set()


def gap_after(arrivals: list[tuple[float, float]], t: float, within: float = 3.0) -> dict:
    """The longest gap in state arrivals (run time, send time; s) that starts between ``t`` - one period
    and ``t`` + ``within``: how long F was dark after event time ``t``, the first state's age after the
    gap, and how long until a state sent after the gap's end (within one period) arrived."""
    times = [a for a, _ in arrivals]
    gaps = [(b - a, i) for i, (a, b) in enumerate(zip(times, times[1:], strict=False))
            if t - 1 / STATE_HZ <= a <= t + within]
    if not gaps:
        return {}
    gap, i = max(gaps)
    end, first_sent = arrivals[i + 1]
    fresh = next((a for a, s in arrivals[i + 1:] if s >= end - 1 / STATE_HZ), None)
    return {"dark_s": gap, "back_at_s": end, "first_age_s": end - first_sent,
            "newest_after_s": None if fresh is None else fresh - end}


def follower_superseded(log: Path) -> int:
    """States F's session superseded while it had no path, as its last resume line printed."""
    lines = [x for x in log.read_text(errors="replace").splitlines() if "rce-ros: session resumed" in x]
    if not lines:
        return 0
    return int(lines[-1].rsplit(" superseded in all", 1)[0].rsplit(", ", 1)[1].split()[0])


async def run(work: Path, out: Path, state_lane: str) -> dict:
    with NetLab("rlb") as lab:
        topo = RelayTopology.make(lab)
        with engine(work / "engine", master_args=("--bind", "0.0.0.0"),
                    robot_args=("--bind", "0.0.0.0", "--advertise-host", topo.cloud_ip)) as e:
            r = await measure(lab, topo, e, work, state_lane)
    r["state_lane"] = state_lane
    r["counted_drops"]["F superseded (to the cloud)"] = follower_superseded(work / "F.log")
    return r


async def measure(lab: NetLab, topo: RelayTopology, e, work: Path, state_lane: str) -> dict:
    url = f"http://{topo.cloud_ip}:{e.http_port}/"
    l1, _ = await start_robot(lab, "l1", robot_config(url, "L1"), work, "--relay-port", str(RELAY_PORT))
    l2, _ = await start_robot(lab, "l2", robot_config(url, "L2"), work, "--relay-port", str(RELAY_PORT))
    for p, name in ((l1, "L1"), (l2, "L2")):
        await wait_text(work / f"{name}.log", "relaying for nearby robots", p)
    f, bus = await start_robot(lab, "f", robot_config(url, "F", echo=True, state_lane=state_lane), work, "--relays",
                               f"{topo.f_l1.a_ip}:{RELAY_PORT},{topo.f_l2.a_ip}:{RELAY_PORT}")
    procs = {"F": f, "L1": l1, "L2": l2}
    try:
        await wait_text(work / "F.log", "rce-ros: ready", f)
        return await streams(lab, topo, e, bus, procs)
    finally:
        for p in procs.values():
            if p.returncode is None:
                p.terminate()
        for p in procs.values():
            await p.wait()


async def streams(lab: NetLab, topo: RelayTopology, e, bus: Path, procs: dict) -> dict:
    node = await rce.node.init_node("bench", bus=str(bus), argv=[])
    rec = Recorder()
    sub = await node.subscriber("/resp", "std_msgs/String", rec, queue_size=HARNESS_QUEUE)
    pub = await node.publisher("/req", "std_msgs/String")
    sent = {"s": 0, "c": 0}

    async def states() -> None:
        while True:
            await pub.publish({"data": f"s:{sent['s']}:{time.monotonic()}"})
            sent["s"] += 1
            await asyncio.sleep(1 / STATE_HZ)           # the stream's period, a timer

    async def commands() -> None:
        while True:
            n = sent["c"]
            await asyncio.to_thread(e.admin, "/api/containers/testUser/cK/publish",
                                    {"topic": "/stringEchoReq", "type": "std_msgs/String",
                                     "msg": {"data": f"c:{n}:{time.monotonic()}"}})
            sent["c"] += 1
            await asyncio.sleep(1 / COMMAND_HZ)         # the stream's period, a timer

    tasks = [asyncio.ensure_future(states())]
    await asyncio.wait_for(rec.first.wait(), ROBOT_WAIT)
    t0 = time.monotonic()
    first_state = min(n for _, k, n, _ in rec.got if k == "s")
    tasks.append(asyncio.ensure_future(commands()))
    ps = {k: psutil.Process(p.pid) for k, p in procs.items()}
    path: list[tuple[float, str]] = []
    cpu: list[tuple[float, dict]] = []
    done = set()
    while (now := time.monotonic() - t0) < END:
        for name, at in EVENTS.items():
            if now >= at and name not in done:
                done.add(name)
                print(f"t={now:5.1f} s: {name}", flush=True)
                if name == "L1 vanishes":
                    lab.set_up(topo.f_l1, False, side="a")
                elif name == "partition":
                    lab.set_up(topo.f_l2, False, side="a")
                elif name == "links back":
                    lab.set_up(topo.f_l1, True, side="a")
                    lab.set_up(topo.f_l2, True, side="a")
                elif name == "L2 gone":
                    lab.set_up(topo.f_l2, False, side="a")
                elif name == "L1 uplink cut":
                    lab.set_up(topo.up1, False, side="b")
                elif name == "L1 uplink back":
                    lab.set_up(topo.up1, True, side="b")
                    lab.route("l1", "default", topo.up1.a_ip)     # the link's down took its routes
                else:
                    topo.direct(True)
        rows = await asyncio.to_thread(e.admin, "/api/robots")
        path.append((now, next((r["relay"] or "direct" for r in rows if r["robot"] == "F"), "none")))
        cpu.append((now, {k: process_cpu_s(p) for k, p in ps.items()}))
        await asyncio.sleep(POLL)                        # the sampling period, a timer
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await asyncio.sleep(DRAIN)                           # the last echoes on their way
    await node.close()
    drops = {name: await asyncio.to_thread(endpoint_counter, e, name)
             for name in ("rce_robot_dropped", "rce_robot_shed", "rce_robot_resume_lost", "rce_robot_duplicates",
                          "rce_robot_superseded")}
    cf = await asyncio.to_thread(e.admin, "/api/containers/testUser/cF/stats")
    drops["container cF"] = {"dropped": cf["dropped"], "echo node dropped": cf["per_node"]["echo"]["dropped"]}
    drops["bench subscriber"] = sub.dropped
    return report(rec, sent, first_state, t0, path, cpu, drops)


def cpu_between(cpu: list, name: str, a: float, b: float) -> float:
    """% of one core process ``name`` used between run times ``a`` and ``b`` (s)."""
    xs = [(t, c[name]) for t, c in cpu if a <= t <= b]
    return 100.0 * (xs[-1][1] - xs[0][1]) / (xs[-1][0] - xs[0][0])


def endpoint_counter(e, name: str) -> float:
    """The sum of robot endpoint metric ``name`` (its samples, all labels)."""
    import urllib.request
    port = e.robot_ready[0]["metrics_port"]
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        text = resp.read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith(name) and not line.startswith(f"{name}_created"))


def report(rec: Recorder, sent: dict, first_state: int, t0: float, path: list, cpu: list, drops: dict) -> dict:
    got = {"s": [n for _, k, n, _ in rec.got if k == "s"], "c": [n for _, k, n, _ in rec.got if k == "c"]}
    count = {k: {n: v.count(n) for n in set(v)} for k, v in got.items()}
    states = [(a - t0, s - t0) for a, k, _, s in rec.got if k == "s"]
    events = {name: gap_after(states, at) for name, at in EVENTS.items() if "back" not in name}
    for cut, back in (("partition", "links back"), ("L1 uplink cut", "L1 uplink back")):
        if events[cut]:            # the part of the gap after the way came back
            events[cut][f"dark_after_{back.replace(' ', '_')}_s"] = events[cut]["back_at_s"] - EVENTS[back]
    # L1 carries F until 20 s, L2 from 20 s to 40 s: the other leader, idle, is the baseline of the same seconds
    relay_cpu = {"L1 relaying (2-19 s)": cpu_between(cpu, "L1", 2, 19),
                 "L2 idle (2-19 s)": cpu_between(cpu, "L2", 2, 19),
                 "L2 relaying (22-39 s)": cpu_between(cpu, "L2", 22, 39),
                 "L1 idle (22-39 s)": cpu_between(cpu, "L1", 22, 39)}
    per_robot = [relay_cpu["L1 relaying (2-19 s)"] - relay_cpu["L2 idle (2-19 s)"],
                 relay_cpu["L2 relaying (22-39 s)"] - relay_cpu["L1 idle (22-39 s)"]]
    changes = [path[0]] + [p for prev, p in zip(path, path[1:], strict=False) if p[1] != prev[1]]
    return {
        "bench": "relay", "git": git_head(), "state_hz": STATE_HZ, "command_hz": COMMAND_HZ, "events_at_s": EVENTS,
        "events": events,
        "commands": {"sent": sent["c"], "received": len(got["c"]),
                     "lost": sum(1 for n in range(sent["c"]) if n not in count["c"]),
                     "duplicated": sum(v - 1 for v in count["c"].values())},
        "states": {"sent": sent["s"] - first_state, "received": len(got["s"]),
                   "lost": sum(1 for n in range(first_state, sent["s"]) if n not in count["s"]),
                   "duplicated": sum(v - 1 for v in count["s"].values()),
                   "in_order": got["s"] == sorted(got["s"])},
        "counted_drops": drops,
        "relay_cpu_percent": relay_cpu, "relay_cpu_per_relayed_robot_percent": per_robot,
        "path": [{"t": round(t, 2), "via": v} for t, v in changes],
        "timeline": {"states": [(round(a, 3), round(a - s, 4)) for a, s in states],
                     "commands": [(round(a - t0, 3), round(a - s, 4)) for a, k, _, s in rec.got if k == "c"]},
    }


def plot(r: dict, png: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(12, 5))
    st, cm = r["timeline"]["states"], r["timeline"]["commands"]
    ax.scatter([a for a, _ in st], [age for _, age in st], s=4, label="state (10 Hz) echo: age at arrival")
    ax.scatter([a for a, _ in cm], [age for _, age in cm], s=24, marker="x", color="C3", label="command (1 Hz): age")
    for name, at in r["events_at_s"].items():
        ax.axvline(at, color="grey", ls="--", lw=0.8)
        ax.text(at + 0.3, 0.97, name, fontsize=8, transform=ax.get_xaxis_transform(), va="top")
    path = r["path"] + [{"t": END, "via": "end"}]
    colors = {"L1": "C0", "L2": "C1", "direct": "C2", "none": "grey"}
    for a, b in zip(path, path[1:], strict=False):
        ax.axvspan(a["t"], b["t"], ymin=0, ymax=0.03, color=colors.get(a["via"], "grey"))
        ax.text(a["t"], -0.02, a["via"], fontsize=7, transform=ax.get_xaxis_transform(), va="top")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("s since the first echo (the band: F's path as the master saw it)")
    ax.set_ylabel("age at arrival, s")
    ax.set_title("bench/relay.py: a follower through relays L1, L2 and its direct link")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=RESULTS / "relay.json")
    p.add_argument("--state-lane", choices=("state", "control"), default="state",
                   help="the state stream's lane (control: every state is kept and replayed after a gap)")
    args = p.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rce-relay-bench-"))
    r = asyncio.run(run(work, args.out, args.state_lane))
    write_json(args.out, r)
    plot(r, args.out.with_suffix(".png"))
    print(json.dumps({k: r[k] for k in ("state_lane", "events", "commands", "states", "counted_drops",
                                        "relay_cpu_percent", "relay_cpu_per_relayed_robot_percent", "path")}, indent=1))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')} (robots' logs in {work})")


if __name__ == "__main__":
    main()
