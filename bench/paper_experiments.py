"""The seed paper's performance experiments (section "Performance Analysis"), ROS 1 single master
against rce, on one machine with the server and the clients in two network namespaces.

- Experiment 1: five simulated robots each publish sensor_msgs/LaserScan (360 beams) at a
  fixed rate (10 Hz) for a fixed time; a server node subscribes to all five ("echoes" them).
- Experiment 2: one publisher streams sensor_msgs/Image (640x480 rgb8, 15 Hz); the server
  node is the one echoing subscriber.

Systems:

- ``ros1``: single master. Server side = ``rosmaster`` + ``bench/ros1/echo.py`` (rospy);
  client side = one ``bench/ros1/robot.py`` (rospy) process per robot. TCPROS, tcp_nodelay.
- ``rce-forwarder`` / ``rce-converter``: server side = the whole engine (rce-master, rce-robot,
  rce-container, the environment) + the container node ``benchecho/echo.py``
  (``bench/packages/benchecho``); client side = one raw-protocol robot process per robot
  (a websocket client speaking the RCE wire protocol, as ``tests/wsclient.RawRobot``), sending
  through a SubscriberForwarder (DM + binary part ``msg*`` with the ROS 1 serialized message)
  or a SubscriberConverter (DM with the message as JSON; uint8[] as base64).

Mode: by default one way, as in the paper (the server only receives, deserializes and counts,
like ``rostopic echo`` without the printing); ``--back`` makes the server publish every message
back to its robot (``TOPIC_echo``), and the robots then report echo counts and latency.

Network bytes: the server runs in one network namespace, the clients in another, joined by a veth
pair; the bytes are the server end's interface counters (``ip -s link``: rx = robots -> server,
tx = server -> robots) over the measured window, so they include Ethernet/IP/TCP headers, ACKs
and everything each system sends (ROS 1's XML-RPC, rce's websocket framing), as a NIC on the
paper's Machine 1 would count. Traffic inside the server side (rce-master <-> rce-robot <->
environment) stays on that namespace's loopback and is not counted, as on the paper's server
machine. Needs root and iproute2; without, everything runs on loopback and bytes are not counted.

CPU: user + system CPU time (psutil) of every server-side process and of every client process
over the same window, as % of one core (200 % = both cores of this 2-core machine).

Usage::

    .venv/bin/python bench/paper_experiments.py [--quick] [--no-ros1] [--back]
        [--systems ros1,rce-forwarder,rce-converter] [--experiments exp1,exp2]
        [--duration S] [--json PATH] [--plot PATH]

Results: ``bench/results/paper_experiments.json`` and ``.png`` by default.
"""
from __future__ import annotations

import argparse
import asyncio
import base64
import contextlib
import json
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

from rce.plumbing.errors import RCEError

from common import (BENCH, CpuMeter, ForeignLoad, NetLab, RawRobot, RESULTS, SYS_PY, USER, VENV_PY, WsRobot, console,
                    engine, ensure_ros1, fmt_ratio, free_port, login, median, percentile, proc_tree, pyplot,
                    set_nice, wait_quiet, write_json)

SYSTEMS = ("ros1", "rce-forwarder", "rce-converter")
EXPERIMENTS = {
    "exp1": {"title": "Experiment 1: 5 robots, LaserScan 360 beams", "kind": "scan", "type": "sensor_msgs/LaserScan",
             "robots": 5, "rate": 10.0, "topic": "scan", "short": "Exp. 1, 5 robots, LaserScan 10 Hz"},
    "exp2": {"title": "Experiment 2: Image 640x480 rgb8, 1 publisher", "kind": "image", "type": "sensor_msgs/Image",
             "robots": 1, "rate": 15.0, "topic": "image", "short": "Exp. 2, Image 640x480 15 Hz"},
}
CTAG = "bench"
PACKAGES = BENCH / "packages"
ROS1_DIR = BENCH / "ros1"


# -- messages (the same content in every system) ------------------------------------------------

def message_json(kind: str) -> dict:
    """JSON form (rce.messages) of the message a robot publishes; header stamped per message."""
    import math
    import random
    hdr = {"seq": 0, "stamp": {"secs": 0, "nsecs": 0}}
    if kind == "scan":
        rnd = random.Random(1)
        return {"header": dict(hdr, frame_id="base_scan"), "angle_min": -math.pi, "angle_max": math.pi,
                "angle_increment": 2 * math.pi / 360, "time_increment": 0.0, "scan_time": 0.1,
                "range_min": 0.12, "range_max": 3.5, "ranges": [rnd.uniform(0.2, 3.5) for _ in range(360)],
                "intensities": []}
    data = bytes(i % 251 for i in range(640 * 480 * 3))
    return {"header": dict(hdr, frame_id="camera"), "height": 480, "width": 640, "encoding": "rgb8",
            "is_bigendian": 0, "step": 640 * 3, "data": base64.b64encode(data).decode()}


def serialized_size(kind: str) -> int:
    from rce.messages import default_registry
    reg = default_registry()
    t = reg.msg_type(EXPERIMENTS["exp1" if kind == "scan" else "exp2"]["type"])
    return len(reg.json_to_bytes(t, message_json(kind)))


# -- rce server (runs in the server namespace) ---------------------------------------------------

async def rce_server(args) -> None:
    """Start the engine, the container with benchecho and the container-side interfaces; print
    ``{"ws_url": ...}``; then answer COUNTS on stdin with the node's last count line, until EXIT."""
    topics = args.topics
    robot_args = ("--bind", "0.0.0.0", "--advertise-host", args.srv_ip) if args.srv_ip != "127.0.0.1" else ()
    with engine(Path(tempfile.mkdtemp(prefix="rce-paper-")), env={"RCE_PACKAGE_PATH": str(PACKAGES)},
                robot_args=robot_args) as eng:
        async with RawRobot(eng.master_url, "benchServer") as r:
            await r.send("CC", {"containerTag": CTAG})
            ifs = []
            for i, t in enumerate(topics):
                ifs.append({"endpointTag": CTAG, "interfaceTag": f"in{i}", "interfaceType": "PublisherInterface",
                            "className": args.type, "addr": t})
                if args.back:
                    ifs.append({"endpointTag": CTAG, "interfaceTag": f"out{i}", "interfaceType": "SubscriberInterface",
                                "className": args.type, "addr": t + "_echo"})
            node_args = ["--type", args.type, *(["--back"] if args.back else []), *topics]
            await r.cn(addNodes=[{"containerTag": CTAG, "nodeTag": "echo", "pkg": "benchecho", "exe": "echo.py",
                                  "args": node_args}], addInterfaces=ifs)
            # the node has subscribed to every topic (bounded wait)
            bus = None
            for _ in range(300):
                try:
                    bus = eng.admin(f"/api/containers/{USER}/{CTAG}/bus")
                except RCEError:      # the container is not there yet
                    await asyncio.sleep(0.1)
                    continue
                subs = {t["name"]: t["subscribers"] for t in bus["topics"]}
                if all(any("echo" in s for s in subs.get(t, [])) for t in topics):
                    break
                await asyncio.sleep(0.1)
            else:
                raise RuntimeError(f"benchecho did not subscribe: {bus}")
            print(json.dumps({"ws_url": login(eng.master_url)["url"]}), flush=True)
            loop = asyncio.get_running_loop()
            while True:
                cmd = (await loop.run_in_executor(None, sys.stdin.readline)).strip()
                if cmd == "COUNTS":
                    logs = eng.admin(f"/api/containers/{USER}/{CTAG}/logs/echo")
                    lines = [ln for ln in logs.get("stdout", []) if ln.startswith("{")]
                    bus = eng.admin(f"/api/containers/{USER}/{CTAG}/bus")
                    print(json.dumps({"node": json.loads(lines[-1]) if lines else None,
                                      "bus": {t["name"]: {k: t[k] for k in ("messages", "bytes", "dropped")}
                                              for t in bus["topics"]}}), flush=True)
                else:
                    break


# -- rce robot (runs in the client namespace) ------------------------------------------------------

async def rce_robot(args) -> int:
    """One simulated robot: robot-side interfaces of its own, connected to the server container's;
    READY / GO / DONE on stdio as bench/ros1/robot.py."""
    from rce.messages import default_registry
    reg = default_registry()
    typ = reg.msg_type(args.type)
    side, i, rid = args.iface, args.index, args.robot
    tmpl = message_json(args.kind)
    msg = reg.from_json(typ, tmpl)
    raw_data = base64.b64decode(tmpl["data"]) if args.kind == "image" else None
    lat: list[float] = []
    st = {"echoes": 0, "measuring": False}
    got = asyncio.Event()
    async with WsRobot(args.ws_url, rid) as r:
        ifs = [{"endpointTag": rid, "interfaceTag": "data", "interfaceType": f"Subscriber{side}",
                "className": args.type}]
        cx = [{"tagA": f"{CTAG}/in{i}", "tagB": f"{rid}/data"}]
        if args.back:
            ifs.append({"endpointTag": rid, "interfaceTag": "echo", "interfaceType": f"Publisher{side}",
                        "className": args.type})
            cx.append({"tagA": f"{CTAG}/out{i}", "tagB": f"{rid}/echo"})
        await r.cn(addInterfaces=ifs)
        await r.send("CX", {"connect": cx})
        await r.wait_up(*(["data", "echo"] if args.back else ["data"]))

        async def reader():
            parts, pending = {}, {}
            async for m in r.ws:
                if isinstance(m, bytes):
                    parts[m[:32].decode()] = m[32:]
                else:
                    d = json.loads(m)
                    if d.get("type") != "DM":
                        continue
                    if "msg" in d["data"]:
                        stamp = d["data"]["msg"]["header"]["stamp"]
                        on_echo(stamp["secs"] + stamp["nsecs"] * 1e-9)
                        continue
                    pending[d["data"]["msg*"]] = d["data"]
                for ref in [k for k in pending if k in parts]:
                    pending.pop(ref)
                    s = reg.deserialize(typ, parts.pop(ref)).header.stamp
                    on_echo(s.sec + s.nanosec * 1e-9)

        def on_echo(stamp: float) -> None:
            got.set()
            if st["measuring"]:
                st["echoes"] += 1
                lat.append((time.time() - stamp) * 1000)

        rtask = asyncio.create_task(reader())

        async def publish(seq: int) -> None:
            now = time.time()
            msg.header.seq = seq
            msg.header.stamp.sec, msg.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
            if side == "Forwarder":
                ref = uuid.uuid4().hex
                payload = reg.serialize(typ, msg)
                await r.ws.send(json.dumps({"type": "DM", "data": {"iTag": "data", "type": args.type, "msgID": "",
                                                                   "msg*": ref}}))
                await r.ws.send(ref.encode() + payload)
            else:
                body = dict(tmpl, header={"seq": seq, "stamp": {"secs": int(now), "nsecs": int((now % 1) * 1e9)},
                                          "frame_id": tmpl["header"]["frame_id"]})
                if raw_data is not None:       # a new camera frame is encoded for every message
                    body["data"] = base64.b64encode(raw_data).decode()
                await r.ws.send(json.dumps({"type": "DM", "data": {"iTag": "data", "type": args.type, "msgID": "",
                                                                   "msg": body}}))

        if args.back:              # warm up: until the first echo comes back (bounded)
            for _ in range(120):
                await publish(0)
                try:
                    await asyncio.wait_for(got.wait(), 0.5)
                    break
                except (TimeoutError, asyncio.TimeoutError):
                    continue
            else:
                print("FAIL no echo", flush=True)
                return 1
            await asyncio.sleep(0.3)
        else:
            await asyncio.sleep(0.3)
        print("READY", flush=True)
        loop = asyncio.get_running_loop()
        if (await loop.run_in_executor(None, sys.stdin.readline)).strip() != "GO":
            return 1
        st["measuring"] = True
        period, sent = 1.0 / args.rate, 0
        t0 = base = time.monotonic()
        while base + sent * period - t0 < args.duration - 1e-6:
            slot, now = base + sent * period, time.monotonic()
            if now < slot:
                await asyncio.sleep(slot - now)
            elif now > slot + period:      # behind by more than a period: no burst to catch up (as rospy.Rate)
                base = now - sent * period
            await publish(sent)
            sent += 1
        elapsed = args.duration
        end = time.monotonic() + 2.0
        while args.back and st["echoes"] < sent and time.monotonic() < end:
            await asyncio.sleep(0.02)
        await asyncio.sleep(0.3)
        st["measuring"] = False
        res = {"sent": sent, "elapsed_s": elapsed, "rate_hz": sent / elapsed if elapsed else 0.0,
               "echoes": st["echoes"] if args.back else None,
               "latency_ms_median": median(lat) if lat else None,
               "latency_ms_p90": percentile(lat, 90) if lat else None}
        print("DONE " + json.dumps(res), flush=True)
        await loop.run_in_executor(None, sys.stdin.readline)
        rtask.cancel()
    return 0


# -- the orchestrator --------------------------------------------------------------------------

class Proc:
    """A child process with a stdout line queue (a reader thread) and stdin lines."""

    def __init__(self, argv: list[str], env: dict | None = None, log: Path | None = None):
        self.argv = argv
        self.p = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=open(log, "wb") if log else subprocess.DEVNULL,
                                  env=env, text=True, bufsize=1, start_new_session=True)
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def expect(self, prefix: str, timeout: float, keep: bool = False) -> str:
        """The next stdout line starting with ``prefix`` (without it unless ``keep``); skips others."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise TimeoutError(f"{self.argv[-1] if len(self.argv) < 4 else ' '.join(self.argv[:6])}: "
                                   f"no {prefix!r} within {timeout:.0f} s") from None
            if line is None:
                raise RuntimeError(f"{' '.join(self.argv[:6])} ... exited ({self.p.wait()}) before {prefix!r}")
            if line.startswith(prefix):
                return line if keep else line[len(prefix):].strip()

    def say(self, line: str) -> None:
        try:
            self.p.stdin.write(line + "\n")
            self.p.stdin.flush()
        except (BrokenPipeError, OSError):
            pass

    def stop(self, timeout: float = 15.0) -> None:
        self.say("EXIT")
        try:
            self.p.stdin.close()
        except OSError:
            pass
        self.wait(timeout)

    def wait(self, timeout: float) -> None:
        try:
            self.p.wait(timeout)
        except subprocess.TimeoutExpired:
            self.p.terminate()
            try:
                self.p.wait(5)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait()


def last_json_line(path: Path) -> dict | None:
    try:
        lines = [ln for ln in path.read_text().splitlines() if ln.startswith("{")]
    except OSError:
        return None
    return json.loads(lines[-1]) if lines else None


class RceServer:
    """The rce server side of one experiment (engine + container + benchecho), shared by the
    rce-forwarder and rce-converter runs of that experiment (robots of each run have their own IDs)."""

    def __init__(self):
        self.proc: Proc | None = None
        self.exp = None

    def get(self, lab: NetLab, exp: str, args, wd: Path) -> Proc:
        if self.proc is not None and self.exp == exp:
            return self.proc
        self.stop()
        spec = EXPERIMENTS[exp]
        topics = [f"/robot{i}/{spec['topic']}" for i in range(spec["robots"])]
        srv = Proc(lab.wrap_srv([VENV_PY, __file__, "_rce-server", "--type", spec["type"], "--srv-ip", lab.srv_ip,
                                 *(["--back"] if args.back else []), *topics]), log=wd / "server.err")
        try:
            srv.ws_url = json.loads(srv.expect("{", 120, keep=True))["ws_url"]
        except BaseException:
            srv.stop(30)
            raise
        self.proc, self.exp = srv, exp
        return srv

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.stop(60)
        self.proc = self.exp = None

    close = stop


def run_one(lab: NetLab, system: str, exp: str, args, workdir: Path, rce_srv: RceServer) -> dict:
    spec = EXPERIMENTS[exp]
    n, rate, typ, kind = spec["robots"], spec["rate"], spec["type"], spec["kind"]
    topics = [f"/robot{i}/{spec['topic']}" for i in range(n)]
    back = ["--back"] if args.back else []
    server_procs: list[Proc | subprocess.Popen] = []
    clients: list[Proc] = []
    wd = workdir / f"{exp}-{system}"
    wd.mkdir(parents=True, exist_ok=True)
    tp = {"start": time.monotonic()}
    try:
        # server side
        if system == "ros1":
            port = 11311 if lab.ok else free_port()
            master = f"http://{lab.srv_ip}:{port}"
            senv = dict(os.environ, ROS_MASTER_URI=master, ROS_HOSTNAME=lab.srv_ip, ROS_HOME=str(wd / "roshome"))
            rm = subprocess.Popen(lab.wrap_srv(["rosmaster", "--core", "-p", str(port)]), env=senv,
                                  stdout=open(wd / "rosmaster.log", "wb"), stderr=subprocess.STDOUT,
                                  start_new_session=True)
            server_procs.append(rm)
            echo_log = wd / "echo.out"
            ep = subprocess.Popen(lab.wrap_srv([SYS_PY, str(ROS1_DIR / "echo.py"), "--type", typ, *back, *topics]),
                                  env=senv, stdout=open(echo_log, "w"), stderr=open(wd / "echo.err", "wb"),
                                  start_new_session=True)
            server_procs.append(ep)
            deadline = time.monotonic() + 60
            while last_json_line(echo_log) is None:
                if ep.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"ROS 1 echo node not up: {(wd / 'echo.err').read_text()[-800:]}")
                time.sleep(0.1)
            server_pids = [rm.pid, ep.pid]
            cenv = dict(os.environ, ROS_MASTER_URI=master, ROS_HOSTNAME=lab.cli_ip, ROS_HOME=str(wd / "roshome"))
            for i, t in enumerate(topics):
                clients.append(Proc(lab.wrap_cli([SYS_PY, str(ROS1_DIR / "robot.py"), "--name", f"robot{i}",
                                                  "--topic", t, "--kind", kind, "--rate", str(rate),
                                                  "--duration", str(args.duration), *back]),
                                    env=cenv, log=wd / f"robot{i}.err"))

            def server_counts():
                time.sleep(0.3)           # the echo node prints its counts every 0.2 s
                return {"node": last_json_line(echo_log)}
        else:
            side = "Forwarder" if system == "rce-forwarder" else "Converter"
            srv = rce_srv.get(lab, exp, args, wd)
            server_pids = [srv.p.pid]
            for i, _topic in enumerate(topics):
                clients.append(Proc(lab.wrap_cli([VENV_PY, __file__, "_rce-robot", "--ws-url", srv.ws_url,
                                                  "--robot", f"{system.split('-')[1]}{i}",
                                                  "--index", str(i), "--iface", side, "--type", typ, "--kind", kind,
                                                  "--rate", str(rate), "--duration", str(args.duration), *back]),
                                    log=wd / f"robot{i}.err"))

            def server_counts():
                time.sleep(0.3)
                srv.say("COUNTS")
                return json.loads(srv.expect("{", 30, keep=True))
        tp["server_up"] = time.monotonic()
        for c in clients:
            c.expect("READY", 120)
        tp["clients_ready"] = time.monotonic()
        time.sleep(0.2)
        c0 = server_counts()
        sproc = [p for p in proc_tree(server_pids) if system == "ros1" or p.pid != server_pids[0]]
        cproc = proc_tree([c.p.pid for c in clients])
        scpu, ccpu = CpuMeter(sproc), CpuMeter(cproc)
        net0 = lab.counters()
        fl = ForeignLoad().start()
        scpu.start()
        ccpu.start()
        for c in clients:
            c.say("GO")
        done = [json.loads(c.expect("DONE", args.duration + 60)) for c in clients]
        scpu.stop()
        ccpu.stop()
        load = fl.stop()
        net1 = lab.counters()
        c1 = server_counts()
        tp["measured"] = time.monotonic()
    finally:
        for c in clients:           # all at once, then wait for each
            c.say("EXIT")
        for c in clients:
            c.stop()
        for p in reversed(server_procs):
            if isinstance(p, Proc):
                p.stop(60)
            elif p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()

    tp["stopped"] = time.monotonic()
    wall = scpu.wall
    sent = sum(d["sent"] for d in done)
    recv = None
    if c0.get("node") and c1.get("node"):
        recv = sum(c1["node"]["counts"][t] - c0["node"]["counts"].get(t, 0) for t in topics)
    msg_bytes = serialized_size(kind)
    out = {"system": system, "experiment": exp, "robots": n, "rate_hz": rate, "duration_s": args.duration,
           "mode": "back" if args.back else "one-way", "msg_bytes": msg_bytes, "wall_s": wall,
           "sent": sent, "server_received": recv,
           "delivered_pct": 100.0 * recv / sent if recv is not None and sent else None,
           "client_rate_hz": sum(d["rate_hz"] for d in done) / len(done),
           "echoes": sum(d["echoes"] for d in done) if args.back else None,
           "latency_ms_median": median([d["latency_ms_median"] for d in done if d["latency_ms_median"] is not None])
           if args.back else None,
           "cpu": {"server_pct": scpu.percent(), "client_pct": ccpu.percent(),
                   "server_by_proc": scpu.by_label(), "client_by_proc": ccpu.by_label()},
           "machine_load": load,
           "payload_kBps": msg_bytes * sent / wall / 1e3 if wall else None,
           "phases_s": {"server_setup": tp["server_up"] - tp["start"],
                        "clients_setup": tp["clients_ready"] - tp["server_up"],
                        "measure": tp["measured"] - tp["clients_ready"], "teardown": tp["stopped"] - tp["measured"]}}
    if system != "ros1" and c1.get("bus"):
        out["bus_dropped"] = sum(v["dropped"] for v in c1["bus"].values())
    if net0 and net1:
        d = {k: net1[k] - net0[k] for k in net0}
        out["net"] = {**d, "rx_kBps": d["rx_bytes"] / wall / 1e3, "tx_kBps": d["tx_bytes"] / wall / 1e3,
                      "total_kBps": (d["rx_bytes"] + d["tx_bytes"]) / wall / 1e3}
        out["net"]["overhead_vs_payload"] = (out["net"]["total_kBps"] / out["payload_kBps"] / (2 if args.back else 1)
                                             if out["payload_kBps"] else None)
    else:
        out["net"] = None
    return out


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short runs (smoke test): 1 s each")
    p.add_argument("--duration", type=float, default=None, help="seconds each robot publishes (default 20; --quick: 1)")
    p.add_argument("--systems", default=",".join(SYSTEMS), help=f"comma list of {','.join(SYSTEMS)}")
    p.add_argument("--experiments", default="exp1,exp2", help="comma list of exp1,exp2")
    p.add_argument("--no-ros1", action="store_true", help="skip ROS 1 (no apt-get)")
    p.add_argument("--back", action="store_true", help="the server echoes every message back to its robot")
    p.add_argument("--nice", type=int, default=None, metavar="N",
                   help="run the bench and all it starts at niceness N (e.g. -10 as root on a shared machine)")
    p.add_argument("--wait-quiet", type=float, default=0.0, metavar="S",
                   help="first wait up to S s for other processes to use < 0.3 cores (shared machines)")
    p.add_argument("--json", type=Path, default=RESULTS / "paper_experiments.json")
    p.add_argument("--plot", type=Path, default=RESULTS / "paper_experiments.png")
    return p.parse_args(argv)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_rce-server":
        p = argparse.ArgumentParser()
        p.add_argument("--type")
        p.add_argument("--srv-ip")
        p.add_argument("--back", action="store_true")
        p.add_argument("topics", nargs="+")
        asyncio.run(rce_server(p.parse_args(argv[1:])))
        return 0
    if argv and argv[0] == "_rce-robot":
        p = argparse.ArgumentParser()
        for k in ("--ws-url", "--robot", "--iface", "--type", "--kind"):
            p.add_argument(k)
        p.add_argument("--index", type=int)
        p.add_argument("--rate", type=float)
        p.add_argument("--duration", type=float)
        p.add_argument("--back", action="store_true")
        return asyncio.run(rce_robot(p.parse_args(argv[1:])))

    args = parse_args(argv)
    args.duration = args.duration or (1.0 if args.quick else 20.0)
    con = console()
    systems = [s for s in args.systems.split(",") if s]
    exps = [e for e in args.experiments.split(",") if e]
    bad = [s for s in systems if s not in SYSTEMS] + [e for e in exps if e not in EXPERIMENTS]
    if bad:
        con.print(f"[red]unknown system/experiment {bad}")
        return 2
    notes = []
    if args.no_ros1 and "ros1" in systems:
        systems.remove("ros1")
    if "ros1" in systems:
        ok, why = ensure_ros1(log=con.print)
        if not ok:
            systems.remove("ros1")
            notes.append(f"ROS 1 skipped: {why}")
            con.print(f"[yellow]ROS 1 skipped: {why}")
    workdir = Path(tempfile.mkdtemp(prefix="rce-paper-"))
    runs = []
    set_nice(args.nice, log=con.print)
    wait_quiet(args.wait_quiet, log=con.print)
    rce_srv = RceServer()
    with NetLab() as lab, contextlib.closing(rce_srv):
        if not lab.ok:
            notes.append(lab.reason)
            con.print(f"[yellow]{lab.reason}")
        for exp in exps:
            for system in systems:
                with con.status(f"{EXPERIMENTS[exp]['title']}: {system} ({args.duration:.0f} s) ..."):
                    res = run_one(lab, system, exp, args, workdir, rce_srv)
                runs.append(res)
                if res["machine_load"]["other_cores"] > 0.25:
                    notes.append(f"{exp} {system}: other processes kept {res['machine_load']['other_cores']:.2f} cores "
                                 f"busy during the window; CPU % and rates are perturbed")
                con.print(f"{exp} {system}: sent {res['sent']}, server got {res['server_received']}, "
                          f"server CPU {res['cpu']['server_pct']:.1f} %, client CPU {res['cpu']['client_pct']:.1f} %"
                          + (f", {res['net']['total_kBps']:.1f} kB/s" if res["net"] else ""))
    out = {"experiments": {k: v for k, v in EXPERIMENTS.items() if k in exps}, "systems": systems,
           "mode": "back" if args.back else "one-way", "duration_s": args.duration,
           "network_method": ("veth between a server and a client network namespace; server-end interface counters "
                              "(ip -s link), rx = robots -> server, tx = server -> robots; frames with headers")
           if lab.ok else None,
           "cpu_method": "psutil user+system CPU time of all server-side / client processes over the window, "
                         "% of one core",
           "rce_client": "raw RCE wire protocol websocket client per robot (forwarder: DM + binary msg*; "
                         "converter: JSON DM)",
           "nice": args.nice, "runs": runs, "notes": notes, "logs": str(workdir)}
    write_json(args.json, out)
    print_table(con, out)
    plot(out, args.plot)
    con.print(f"results: {args.json}  plot: {args.plot}  logs: {workdir}")
    return 0


SHORT = {"rce_container.environment": "env", "rce-container": "container", "rce-robot": "robot",
         "rce-master": "master", "echo.py": "echo"}
LABEL = {"ros1": "SMS (ROS 1)", "rce-forwarder": "CRS (rce fwd)", "rce-converter": "CRS (rce conv)"}


def print_table(con, out: dict) -> None:
    from rich.table import Table
    for exp in out["experiments"]:
        runs = [r for r in out["runs"] if r["experiment"] == exp]
        if not runs:
            continue
        t = Table(title=f"{EXPERIMENTS[exp]['title']} ({runs[0]['msg_bytes']} B serialized) @ "
                        f"{EXPERIMENTS[exp]['rate']:g} Hz, {out['duration_s']:g} s, {out['mode']}")
        for c in ("system", "rate Hz", "deliv. %", "in kB/s", "out kB/s", "net/payload",
                  "server CPU %", "client CPU %", "other load", "server CPU % by process"):
            t.add_column(c, justify="left" if c in ("system", "server CPU % by process") else "right")
        for r in runs:
            net = r["net"]
            t.add_row(LABEL[r["system"]], f"{r['client_rate_hz']:.2f}",
                      "-" if r["delivered_pct"] is None else f"{r['delivered_pct']:.1f}",
                      f"{net['rx_kBps']:.1f}" if net else "-", f"{net['tx_kBps']:.1f}" if net else "-",
                      fmt_ratio(net["overhead_vs_payload"]) if net else "-",
                      f"{r['cpu']['server_pct']:.1f}", f"{r['cpu']['client_pct']:.1f}",
                      f"{r['machine_load']['other_cores']:.2f}",
                      ", ".join(f"{SHORT.get(k, k)} {v:.1f}" for k, v in list(r["cpu"]["server_by_proc"].items())[:4]))
        con.print(t)
    for n in out["notes"]:
        con.print(f"[yellow]note: {n}")


def plot(out: dict, path: Path) -> None:
    plt = pyplot()
    exps = list(out["experiments"])
    fig, axes = plt.subplots(len(exps), 2, figsize=(11, 3.6 * len(exps)), squeeze=False)
    for row, exp in zip(axes, exps, strict=False):
        runs = [r for r in out["runs"] if r["experiment"] == exp]
        names = [LABEL[r["system"]] for r in runs]
        x = range(len(runs))
        ax = row[0]
        if all(r["net"] for r in runs):
            ax.bar([i - 0.2 for i in x], [r["net"]["rx_kBps"] for r in runs], 0.4, label="in (robots -> server)")
            ax.bar([i + 0.2 for i in x], [r["net"]["tx_kBps"] for r in runs], 0.4, label="out (server -> robots)")
            ax.plot(list(x), [r["payload_kBps"] for r in runs], "k_", markersize=30, linestyle="none",
                    label="serialized payload")
            ax.legend(fontsize=8)
        else:
            ax.text(0.5, 0.5, "network bytes not counted", ha="center", transform=ax.transAxes)
        ax.set_xticks(list(x), names)
        ax.set_ylabel("server network, kB/s")
        ax.set_title(f"{EXPERIMENTS[exp]['short']}: server network", fontsize=10)
        ax = row[1]
        ax.bar([i - 0.2 for i in x], [r["cpu"]["server_pct"] for r in runs], 0.4, label="server (-S)")
        ax.bar([i + 0.2 for i in x], [r["cpu"]["client_pct"] for r in runs], 0.4, label="clients (-C)")
        for i, r in zip(x, runs, strict=False):
            ax.annotate(f"{r['client_rate_hz']:.1f} Hz", (i, max(r["cpu"]["server_pct"], r["cpu"]["client_pct"])),
                        ha="center", va="bottom", fontsize=8)
        ax.set_xticks(list(x), names)
        ax.set_ylabel("CPU, % of one core")
        ax.set_title(f"{EXPERIMENTS[exp]['short']}: CPU (achieved publish rate on top)", fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
