"""``rce-topic`` and ``rce-service``: rostopic/rosservice for any RCE bus.

::

    rce-topic list [-v]
    rce-topic echo TOPIC [-n N] [--type T]
    rce-topic pub TOPIC [TYPE] YAML_MSG [-r HZ] [-n N] [-1/--once]
    rce-topic hz TOPIC [-w WINDOW] [--type T] [--reports N]
    rce-topic type TOPIC | info TOPIC
    rce-topic record -o FILE.bag TOPIC... [--duration S] [--count N]
    rce-service list [-v]
    rce-service call SERVICE [YAML_REQ] [--type T] [--timeout S]
    rce-service type SERVICE

Which bus (options go before or after the command):

- a local bus (the robot's, run by ``rce-ros``): ``--bus PATH``, else ``$RCE_BUS``, else the
  only socket in ``$XDG_RUNTIME_DIR/rce`` (``/tmp/rce-<uid>``);
- a container's bus through the master's admin API (:mod:`rce.tools.admin_client`):
  ``--container CTAG --master URL --user U`` with a token from ``--admin-token``,
  ``$RCE_ADMIN_TOKEN``, ``--admin-token-file`` or ``~/.config/rce/admin-token``
  (``$XDG_CONFIG_HOME/rce/admin-token``).

Messages are YAML as with rostopic (``'{data: hello}'``), in the JSON form of
:mod:`rce.messages`. A TYPE left out is taken from the bus (``describe``). ``echo`` prints
YAML documents separated by ``---``; ``pub`` without ``-r`` publishes once and exits (the
bus does not latch). Exit codes: 0 ok, 1 failure (reason on stderr), 2 usage.

``record`` writes a ROS 1 bag (:mod:`rce_client.bag`) until Ctrl-C or SIGTERM, ``--duration``
S seconds or ``--count`` N messages (all topics together); a topic not published yet is
recorded from when it appears. On a local bus every message is recorded (a subscription
with a queue of :data:`RECORD_QUEUE`; what overflows is counted and reported). Through the
admin API a container's topics are sampled one message per request, as ``echo`` does: a
message published during a request's round trip is not recorded (fine for a fleet's rates;
for every message, record on a robot's bus or through forwarders, :func:`rce_client.bag.record_container`).
"""
from __future__ import annotations

import argparse
import asyncio
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable

import yaml

from rce.transport import tls
from rce.tools.admin_client import AdminClient
from rce.plumbing.errors import MessageError, NotFound, RCEError, RequestError, Unavailable
from rce.plumbing.log import setup_logging
from rce.messages import MessageRegistry, default_registry
from rce.interfaces.naming import resolve
from rce.node.package_path import load_package_types
from rce.plumbing.process import exit_command, run_loop
from rce.plumbing.tasks import Tasks
from rce_client.bag import BagRecorder
from rce_client.paths import bus_dir, running_buses

POLL = 0.2          # s between describe polls while waiting for a topic to appear
ECHO_SAMPLE_TIMEOUT = 5.0   # s, one admin API sample of ``echo --container`` (then the next one)
SERVICE_WAIT = 10.0         # s, ``rce-service call`` waits at most this (or --timeout) for the service to appear
HZ_PERIOD = 1.0             # s between ``rce-topic hz`` reports (as rostopic hz)
RECORD_QUEUE = 10000        # messages a recorded topic may have waiting on a local bus (oldest dropped, counted)
RECORD_SAMPLE_TIMEOUT = 1.0  # s, one admin API sample of ``record --container`` (then the next: a stop is seen)


# -- output ----------------------------------------------------------------------------------
class _Dumper(yaml.SafeDumper):
    pass


def _str_repr(dumper: yaml.SafeDumper, text: str):
    style = "|" if "\n" in text else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", text, style=style)


_Dumper.add_representer(str, _str_repr)


def to_yaml(msg: Any) -> str:
    """A JSON-form message as rostopic prints it: block YAML, multi-line strings as literal blocks."""
    return yaml.dump(msg, Dumper=_Dumper, default_flow_style=False, sort_keys=False, allow_unicode=True).rstrip("\n")


def parse_yaml(text: str, what: str) -> dict:
    """Parse a YAML message/request argument (``'{data: hello}'``); empty means ``{}``.
    Raises :class:`MessageError` when it is not YAML or not a mapping."""
    try:
        obj = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as e:
        raise MessageError(f"{what} is not valid YAML: {e}") from None
    if obj is None:
        return {}
    if not isinstance(obj, dict):
        raise MessageError(f"{what} must be a YAML mapping like '{{data: hello}}', got {type(obj).__name__}")
    return obj


def _global(name: str) -> str:
    return resolve(name, "/")


# -- backends --------------------------------------------------------------------------------
class LocalBus:
    """A local bus (Unix socket) through :mod:`rce.node`."""

    def __init__(self, path: str):
        self.path = path
        self.node = None

    async def open(self) -> None:
        import rce.node
        self.node = await rce.node.init_node(f"rce_tool_{os.getpid()}", bus=self.path, argv=[])

    async def close(self) -> None:
        if self.node is not None:
            await self.node.close()

    async def describe(self) -> dict:
        return await self.node.describe()

    async def publisher(self, topic: str, type_: str) -> Callable[[dict], Any]:
        pub = await self.node.publisher(topic, type_, queue_size=100)

        async def publish(msg: dict) -> None:
            await pub.publish(msg)
        return publish

    async def flush(self) -> None:
        """Round trip to the bus: everything published before has been routed."""
        await self.node.describe()

    @property
    def registry(self) -> MessageRegistry:
        return self.node.registry

    async def subscribe(self, topic: str, type_: str, cb: Callable[[dict], Any], queue_size: int = 1000) -> None:
        reg = self.node.registry
        store = reg.msg_type(type_)
        await self.node.subscriber(topic, type_, lambda msg: cb(reg.to_json(store, msg)), queue_size=queue_size)

    async def subscribe_raw(self, topic: str, type_: str, cb: Callable[[bytes], Any], queue_size: int) -> Any:
        """Subscribe ``cb(serialized bytes)``; returns the subscriber (its ``dropped`` counts overflow)."""
        reg = self.node.registry
        store = reg.msg_type(type_)
        return await self.node.subscriber(topic, type_, lambda msg: cb(reg.serialize(store, msg)),
                                          queue_size=queue_size)

    async def call(self, service: str, type_: str, request: dict, timeout: float) -> dict:
        reg = self.node.registry
        req_t, resp_t = reg.srv_types(type_)
        proxy = await self.node.service_proxy(service, type_)
        resp = await proxy(request, timeout=timeout)
        return reg.to_json(resp_t, resp)


class AdminBus:
    """A container's bus through the master's admin API (``/api/containers/{user}/{ctag}/...``:
    ``bus``, ``publish``, ``call``, ``sample``); errors as :mod:`rce.tools.admin_client` raises them."""

    def __init__(self, client: AdminClient, user: str, ctag: str):
        self.client, self.user, self.ctag = client, user, ctag
        self.base = f"/api/containers/{user}/{ctag}"
        self._registry: MessageRegistry | None = None

    @property
    def registry(self) -> MessageRegistry:
        """The message classes here (with the node packages' on this machine): the container sends JSON."""
        if self._registry is None:
            self._registry = default_registry()
            load_package_types(self._registry)
        return self._registry

    async def open(self) -> None:
        return None

    async def close(self) -> None:
        await self.client.aclose()

    async def describe(self) -> dict:
        return await self.client.arequest("GET", f"{self.base}/bus")

    async def publisher(self, topic: str, type_: str) -> Callable[[dict], Any]:
        async def publish(msg: dict) -> None:
            await self.client.arequest("POST", f"{self.base}/publish", {"topic": topic, "type": type_, "msg": msg})
        return publish

    async def flush(self) -> None:
        return None

    async def sample(self, topic: str, count: int, timeout: float, type_: str | None = None) -> list[dict]:
        """Up to ``count`` messages of ``topic`` received within ``timeout`` s (JSON form);
        ``type_`` lets the container wait for a topic that does not exist yet."""
        body = {"topic": topic, "count": count, "timeout": timeout}
        if type_:
            body["type"] = type_
        return list(await self.client.arequest("POST", f"{self.base}/sample", body, timeout) or [])

    async def call(self, service: str, type_: str | None, request: dict, timeout: float) -> dict:
        """The JSON response of ``service`` (its type is the container's; ``type_`` is unused)."""
        body = {"service": service, "request": request, "timeout": timeout}
        return await self.client.arequest("POST", f"{self.base}/call", body, timeout)


def pick_backend(args: argparse.Namespace) -> LocalBus | AdminBus:
    """The bus the options name. Raises :class:`Unavailable` when none can be chosen."""
    if args.container:
        missing = [o for o, v in (("--master", args.master), ("--user", args.user)) if not v]
        if missing:
            raise Unavailable(f"--container needs {' and '.join(missing)}")
        return AdminBus(AdminClient.from_options(args.master, args.admin_token, args.admin_token_file, args.ca_file),
                        args.user, args.container)
    path = args.bus or os.environ.get("RCE_BUS")
    if not path:
        found = running_buses()
        if len(found) == 1:
            path = found[0]
        else:
            why = f"{len(found)} buses in {bus_dir()}" if found else "no bus"
            raise Unavailable(f"{why}: pass --bus PATH or set RCE_BUS (rce-ros prints it), "
                              f"or --container CTAG --master URL --user U")
    return LocalBus(path)


async def _find(backend, kind: str, name: str) -> dict | None:
    d = await backend.describe()
    return next((x for x in d.get(kind, []) if x.get("name") == name), None)


async def _topic_type(backend, topic: str, explicit: str | None, wait: bool, err: Callable[[str], None]) -> str:
    """The topic's type: ``explicit``, else from the bus; with ``wait``, poll until it appears."""
    if explicit:
        return explicit
    warned = False
    while True:
        t = await _find(backend, "topics", topic)
        if t is not None:
            return t["type"]
        if not wait:
            raise NotFound(f"topic {topic} is not on the bus (give its type)")
        if not warned:
            err(f"WARNING: topic [{topic}] does not appear to be published yet")
            warned = True
        await asyncio.sleep(POLL)   # polling the bus description, a timer


# -- commands ---------------------------------------------------------------------------------
def _common(parser: argparse.ArgumentParser, suppress: bool) -> None:
    d = {"default": argparse.SUPPRESS} if suppress else {"default": None}
    g = parser.add_argument_group("bus")
    g.add_argument("--bus", metavar="PATH", help="local bus socket (default $RCE_BUS)", **d)
    g.add_argument("--container", metavar="CTAG", help="a container's bus, through the master's admin API", **d)
    g.add_argument("--master", metavar="URL", help="master URL for --container (http://HOST:9000/)", **d)
    g.add_argument("--user", metavar="U", help="owner of the container for --container", **d)
    g.add_argument("--admin-token", metavar="TOKEN", help="admin API token (default $RCE_ADMIN_TOKEN or "
                   "~/.config/rce/admin-token)", **d)
    g.add_argument("--admin-token-file", metavar="PATH", type=Path, help="the master's admin token file "
                   "(default ~/.config/rce/admin-token)", **d)
    g.add_argument("--ca-file", metavar="FILE", type=Path, help="CA certificate(s) of an https:// master "
                   f"(default ${tls.CA_FILE_ENV}, else the system's CAs)", **d)


def _parser(prog: str, desc: str) -> tuple[argparse.ArgumentParser, Any, Callable]:
    p = argparse.ArgumentParser(prog=prog, description=desc)
    _common(p, False)
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    def add(name: str, help_: str) -> argparse.ArgumentParser:
        sp = sub.add_parser(name, help=help_, description=help_)
        _common(sp, True)
        return sp
    return p, sub, add


def topic_parser() -> argparse.ArgumentParser:
    p, _, add = _parser("rce-topic", "Inspect and use the topics of an RCE bus (like rostopic).")
    sp = add("list", "list the topics")
    sp.add_argument("-v", "--verbose", action="store_true", help="with types and publisher/subscriber counts")
    sp = add("echo", "print the messages of a topic")
    sp.add_argument("topic")
    sp.add_argument("-n", type=int, metavar="N", help="exit after N messages")
    sp.add_argument("--type", help="message class (default: from the bus)")
    sp = add("pub", "publish a message on a topic")
    sp.add_argument("topic")
    sp.add_argument("args", nargs="+", metavar="[TYPE] MSG", help="message class (default: from the bus) and "
                    "the message as YAML, e.g. '{data: hello}'")
    sp.add_argument("-r", "--rate", type=float, metavar="HZ", help="publish repeatedly at HZ until Ctrl-C")
    sp.add_argument("-n", type=int, metavar="N", help="with -r: stop after N messages")
    sp.add_argument("-1", "--once", action="store_true", help="publish once and exit (the default)")
    sp = add("hz", "print the publishing rate of a topic")
    sp.add_argument("topic")
    sp.add_argument("-w", "--window", type=int, default=100, metavar="N", help="messages in the window (100)")
    sp.add_argument("--type", help="message class (default: from the bus)")
    sp.add_argument("--reports", type=int, metavar="N", help="exit after N reports")
    sp = add("type", "print the class of a topic")
    sp.add_argument("topic")
    sp = add("info", "print a topic's class, publishers, subscribers and counters")
    sp.add_argument("topic")
    sp = add("record", "record topics into a ROS 1 bag file (like rosbag record)")
    sp.add_argument("topics", nargs="+", metavar="TOPIC")
    sp.add_argument("-o", "--output", required=True, metavar="FILE.bag", help="the bag to write (replaced)")
    sp.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    sp.add_argument("--count", type=int, metavar="N", help="stop after N messages (all topics together)")
    return p


def service_parser() -> argparse.ArgumentParser:
    p, _, add = _parser("rce-service", "Inspect and call the services of an RCE bus (like rosservice).")
    sp = add("list", "list the services")
    sp.add_argument("-v", "--verbose", action="store_true", help="with types and providers")
    sp = add("call", "call a service and print the response")
    sp.add_argument("service")
    sp.add_argument("request", nargs="?", default="{}", metavar="YAML_REQ", help="request as YAML (default {})")
    sp.add_argument("--type", help="service class (default: from the bus)")
    sp.add_argument("--timeout", type=float, default=30.0, metavar="S",
                    help="seconds to wait for the response (30); for the service to appear at most 10")
    sp = add("type", "print the class of a service")
    sp.add_argument("service")
    return p


def _out(text: str) -> None:
    print(text, flush=True)


def _err(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


async def topic_cmd(args: argparse.Namespace, backend) -> int:
    """Run one ``rce-topic`` command on an open backend; returns the exit code."""
    if args.cmd == "list":
        for t in (await backend.describe()).get("topics", []):
            if args.verbose:
                _out(f"{t['name']} [{t['type']}] {len(t.get('publishers', []))} publisher(s), "
                     f"{len(t.get('subscribers', []))} subscriber(s)")
            else:
                _out(t["name"])
        return 0
    if args.cmd == "record":
        return await _record(args, backend)
    topic = _global(args.topic)
    if args.cmd in ("type", "info"):
        t = await _find(backend, "topics", topic)
        if t is None:
            raise NotFound(f"topic {topic} is not on the bus")
        if args.cmd == "type":
            _out(t["type"])
        else:
            _out(f"Type: {t['type']}\n\nPublishers:")
            for p in t.get("publishers", []) or ["None"]:
                _out(f" * {p}")
            _out("\nSubscribers:")
            for s in t.get("subscribers", []) or ["None"]:
                _out(f" * {s}")
            _out(f"\nMessages: {t.get('messages', 0)}  Bytes: {t.get('bytes', 0)}  Dropped: {t.get('dropped', 0)}")
        return 0
    if args.cmd == "pub":
        return await _pub(args, backend, topic)
    if args.cmd == "echo":
        return await _echo(args, backend, topic)
    if args.cmd == "hz":
        return await _hz(args, backend, topic)
    raise RequestError(f"unknown command {args.cmd}")


async def _record(args, backend) -> int:
    """``rce-topic record``: every topic fed into one bag until the duration, the count or a signal."""
    topics = [_global(t) for t in args.topics]
    bag = BagRecorder(args.output, backend.registry)
    bag.open()
    stop = asyncio.Event()
    failures: list[RCEError] = []
    subs: list[Any] = []
    tasks = Tasks("rce-topic record")

    def got(topic: str, cls: str, payload: bytes) -> None:
        if stop.is_set():
            return
        bag.write(topic, cls, payload)
        if args.count is not None and bag.total >= args.count:
            stop.set()

    async def feed(topic: str) -> None:
        try:
            cls = await _topic_type(backend, topic, None, True, _err)
            typename = backend.registry.msg_type(cls)
            _err(f"recording {topic} [{cls}]")
            if not isinstance(backend, AdminBus):
                subs.append(await backend.subscribe_raw(topic, cls, lambda payload: got(topic, cls, payload),
                                                        RECORD_QUEUE))
                return
            while not stop.is_set():
                for m in await backend.sample(topic, 1, RECORD_SAMPLE_TIMEOUT, cls):
                    got(topic, cls, backend.registry.json_to_bytes(typename, m))
        except RCEError as e:
            failures.append(e)
            stop.set()

    for t in topics:
        tasks.spawn(feed(t), name=t)
    _err(f"recording to {args.output} (Ctrl-C to stop)")
    try:
        async with asyncio.timeout(args.duration):
            await stop.wait()
    except TimeoutError:
        pass
    finally:
        stop.set()
        await tasks.cancel_all()
        bag.close()
        dropped = sum(s.dropped for s in subs)
        _err(bag.summary() + (f"; {dropped} dropped (queue of {RECORD_QUEUE} full)" if dropped else ""))
    if failures:
        raise failures[0]
    return 0


async def _pub(args, backend, topic: str) -> int:
    if len(args.args) > 2:
        raise MessageError(f"pub takes TOPIC [TYPE] MSG, got {len(args.args) + 1} arguments (quote the YAML)")
    type_ = args.args[0] if len(args.args) == 2 else None
    msg = parse_yaml(args.args[-1], "message")
    type_ = await _topic_type(backend, topic, type_, False, _err)
    publish = await backend.publisher(topic, type_)
    if not args.rate:
        await publish(msg)
        await backend.flush()
        _err(f"published 1 message on {topic} [{type_}]")
        return 0
    period, n, nxt = 1.0 / args.rate, 0, time.monotonic()
    _err(f"publishing on {topic} [{type_}] at {args.rate:g} Hz (Ctrl-C to stop)")
    while args.n is None or n < args.n:
        await publish(msg)
        n += 1
        nxt += period
        await asyncio.sleep(max(0.0, nxt - time.monotonic()))   # the publishing rate
    await backend.flush()
    return 0


async def _echo(args, backend, topic: str) -> int:
    count = 0
    limit = args.n

    def show(msg: dict) -> None:
        nonlocal count
        if limit is not None and count >= limit:
            return
        count += 1
        _out(to_yaml(msg))
        _out("---")
        if limit is not None and count >= limit:
            done.set()

    done = asyncio.Event()
    if isinstance(backend, AdminBus):
        _err(f"sampling {topic} through the admin API")
        while limit is None or count < limit:
            for m in await backend.sample(topic, min(limit - count, 100) if limit else 10, ECHO_SAMPLE_TIMEOUT,
                                          args.type):
                show(m)
        return 0
    type_ = await _topic_type(backend, topic, args.type, True, _err)
    await backend.subscribe(topic, type_, show)
    _err(f"subscribed to {topic} [{type_}]")
    await done.wait()
    return 0


async def _hz(args, backend, topic: str) -> int:
    if isinstance(backend, AdminBus):
        raise Unavailable("hz needs a live subscription; the admin API only samples (use echo -n N)")
    type_ = await _topic_type(backend, topic, args.type, True, _err)
    stamps: list[float] = []
    total = 0

    def tick(_msg: dict) -> None:
        nonlocal total
        total += 1
        stamps.append(time.monotonic())
        del stamps[:-(args.window + 1)]

    await backend.subscribe(topic, type_, tick)
    _err(f"subscribed to {topic} [{type_}]")
    reports, last_total = 0, 0
    while args.reports is None or reports < args.reports:
        await asyncio.sleep(HZ_PERIOD)   # the report period
        reports += 1
        if total == last_total or len(stamps) < 2:
            _out("no new messages")
            last_total = total
            continue
        last_total = total
        gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
        mean = sum(gaps) / len(gaps)
        std = math.sqrt(sum((g - mean) ** 2 for g in gaps) / len(gaps))
        _out(f"average rate: {1.0 / mean:.3f}\n\tmin: {min(gaps):.3f}s max: {max(gaps):.3f}s "
             f"std dev: {std:.5f}s window: {len(gaps) + 1}")
    return 0


async def service_cmd(args: argparse.Namespace, backend) -> int:
    """Run one ``rce-service`` command on an open backend; returns the exit code."""
    if args.cmd == "list":
        for s in (await backend.describe()).get("services", []):
            _out(f"{s['name']} [{s['type']}] provider {s.get('provider')}" if args.verbose else s["name"])
        return 0
    name = _global(args.service)
    if args.cmd == "type":
        s = await _find(backend, "services", name)
        if s is None:
            raise NotFound(f"service {name} is not on the bus")
        _out(s["type"])
        return 0
    request = parse_yaml(args.request, "request")
    type_ = args.type
    if type_ is None:
        # like `rosservice call --wait`: the node providing it may still be starting
        loop = asyncio.get_running_loop()
        wait = min(args.timeout, SERVICE_WAIT) if args.timeout else SERVICE_WAIT
        deadline = loop.time() + wait
        warned = False
        while (s := await _find(backend, "services", name)) is None:
            if loop.time() >= deadline:
                names = sorted(x["name"] for x in (await backend.describe()).get("services", []))
                raise NotFound(f"service {name} is not on the bus (waited {wait:g} s); "
                               f"the bus has {', '.join(names) if names else 'no service'}")
            if not warned:
                _err(f"WARNING: service [{name}] is not on the bus yet; waiting up to {wait:g} s")
                warned = True
            await asyncio.sleep(POLL)   # polling the bus description, a timer
        type_ = s["type"]
    resp = await backend.call(name, type_, request, args.timeout)
    _out(to_yaml(resp) if resp else "")
    return 0


def _run(prog: str, parser: argparse.ArgumentParser, cmd, argv: list[str] | None) -> None:
    """Run ``cmd`` and exit with its code (:func:`~rce.plumbing.process.exit_command`)."""
    args = parser.parse_args(argv)
    setup_logging(level=os.environ.get("RCE_LOG_LEVEL", "WARNING"))

    async def amain() -> int:
        backend = pick_backend(args)
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, task.cancel)
        await backend.open()
        try:
            return await cmd(args, backend)
        finally:
            await backend.close()

    try:
        code = run_loop(amain())
    except asyncio.CancelledError:
        code = 0
    except RCEError as e:
        _err(f"{prog}: {e.message}")
        code = 1
    except KeyboardInterrupt:
        code = 0
    exit_command(code, argv)


def topic_main(argv: list[str] | None = None) -> None:
    """Entry point of ``rce-topic``."""
    _run("rce-topic", topic_parser(), topic_cmd, argv)


def service_main(argv: list[str] | None = None) -> None:
    """Entry point of ``rce-service``."""
    _run("rce-service", service_parser(), service_cmd, argv)
