"""Network namespaces and veth links that a test or benchmark makes for itself (as root) and deletes
on exit, also after a failure, and reaps when a killed run left them (docs/testing.md)::

    with NetLab("rly") as lab:
        f = lab.namespace("f")                        # a namespace with its loopback up
        up = lab.link(None, "l1", 1)                   # root <-> l1: 10.201.1.1/30 <-> 10.201.1.2/30
        lab.route("l1", "default", up.a_ip)
        subprocess.Popen(lab.wrap("l1", ["rce-ros", ...]))
        lab.set_up(up, False, side="b")                # l1's end down: packets into it are lost silently
        far = lab.link(None, "f", 2, delay=True)       # with a delay line in the middle (rce.tools.delayline)
        lab.set_delay(far, 50)                         # 50 ms each way from now on

Addresses are ``10.S.N.1`` (side a) and ``10.S.N.2`` (side b) for link number N, with S the first of
:data:`SUBNETS` that no address of the root namespace uses and no other lab holds (so that labs of runs at
the same time do not clash).
"""
from __future__ import annotations

import fcntl
import os
import re
import subprocess
import sys
from dataclasses import dataclass

from rce.tools import delayline

SUBNETS = range(201, 250)   # second octets a NetLab may give its addresses
LOCK_DIR = "/run/rce-netlab"   # where labs hold their subnets (flock)


@dataclass(frozen=True)
class Link:
    """A veth pair between namespace ``a`` (None: the root namespace) and ``b``: devices and addresses."""
    a: str | None
    b: str
    a_dev: str
    b_dev: str
    a_ip: str
    b_ip: str
    control: str | None = None     # the control socket of the delay line in its middle, if it has one


class NetLab:
    """Namespaces named ``PREFIX<pid>-<name>`` and the veth links between them; needs root (``ip``)."""

    def __init__(self, prefix: str):
        self.prefix = f"{prefix}{os.getpid()}"
        self.namespaces: list[str] = []
        self.links: list[Link] = []
        self.subnet = SUBNETS[0]
        self._lock: int | None = None          # the fd holding this lab's subnet (flock), closed with it
        self._delay_lines: list[subprocess.Popen] = []

    def __enter__(self) -> "NetLab":
        self._reap_stale()
        self.subnet = self._take_subnet()
        return self

    def _take_subnet(self) -> int:
        """The first of :data:`SUBNETS` that no root address uses and no other lab holds: each lab holds an
        exclusive ``flock`` on ``LOCK_DIR/10.S.lock`` while it lives (released by the kernel if it dies), so
        labs started at the same moment (parallel tests) never pick the same. Raises :class:`RuntimeError`
        when every one is taken."""
        os.makedirs(LOCK_DIR, exist_ok=True)
        used = subprocess.run(["ip", "-br", "addr"], capture_output=True, text=True).stdout
        for s in SUBNETS:
            fd = os.open(os.path.join(LOCK_DIR, f"10.{s}.lock"), os.O_RDWR | os.O_CREAT, 0o600)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                continue
            if f" 10.{s}." in used:
                os.close(fd)
                continue
            self._lock = fd
            return s
        raise RuntimeError(f"every NetLab subnet 10.{SUBNETS[0]}-{SUBNETS[-1]}.x.x is taken")

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Delete every link's root end and every namespace made (the kernel may tear a namespace's devices
        down later, so the root ends are deleted here rather than left to it)."""
        for p in self._delay_lines:
            p.terminate()
        for p in self._delay_lines:
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self._delay_lines.clear()
        for link in self.links:
            if link.a is None:
                subprocess.run(["ip", "link", "del", link.a_dev], capture_output=True)
        self.links.clear()
        for ns in self.namespaces:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.namespaces.clear()
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def _reap_stale(self) -> None:
        """Delete namespaces of this prefix, and root ends of links, left by a run that was killed (its pid
        is gone)."""
        base = re.escape(self.prefix.rstrip("0123456789"))
        r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
        for line in r.stdout.splitlines():
            m = re.match(rf"({base}(\d+)-\S+)", line)
            if m and not os.path.exists(f"/proc/{m.group(2)}"):
                subprocess.run(["ip", "netns", "del", m.group(1)], capture_output=True)
        r = subprocess.run(["ip", "-br", "link"], capture_output=True, text=True)
        for line in r.stdout.splitlines():
            m = re.match(r"(v(\d+)a\d+)@", line)
            if m and not os.path.exists(f"/proc/{m.group(2)}"):
                subprocess.run(["ip", "link", "del", m.group(1)], capture_output=True)

    @staticmethod
    def ip(*args: str) -> None:
        """Run ``ip ARGS``; raises :class:`subprocess.CalledProcessError` with its stderr."""
        subprocess.run(["ip", *args], check=True, capture_output=True, text=True)

    def namespace(self, name: str) -> str:
        """Make namespace ``name`` (loopback up); returns its full name."""
        ns = f"{self.prefix}-{name}"
        self.ip("netns", "add", ns)
        self.namespaces.append(ns)
        self.ip("-n", ns, "link", "set", "lo", "up")
        return ns

    def full(self, name: str | None) -> str | None:
        """The full name of namespace ``name`` (None: the root namespace)."""
        return None if name is None else f"{self.prefix}-{name}"

    def link(self, a: str | None, b: str, n: int, delay: bool = False) -> Link:
        """A veth pair between namespaces ``a`` (None: root) and ``b`` (short names, made already) with
        addresses ``10.S.n.1/30`` and ``.2/30`` (S: :attr:`subnet`), both ends up.

        ``delay``: the link is two veth pairs bridged by a delay line (:mod:`rce.tools.delayline`) in a
        namespace of its own (``dlN``), which holds every frame :meth:`set_delay` ms each way (0 until
        then); the ends, their addresses and their shaping (:meth:`shape`) are as without it. Raises
        RuntimeError when the delay line does not start."""
        a_dev, b_dev = f"v{os.getpid()}a{n}", f"v{os.getpid()}b{n}"
        fa, fb = self.full(a), self.full(b)
        control = None
        if not delay:
            self._veth(a_dev, fa, b_dev, fb)
        else:
            mid = self.namespace(f"dl{n}")
            m_a, m_b = f"v{os.getpid()}p{n}", f"v{os.getpid()}q{n}"
            self._veth(a_dev, fa, m_a, mid)
            self._veth(m_b, mid, b_dev, fb)
            for dev in (m_a, m_b):
                self.ip("-n", mid, "link", "set", dev, "up")
            control = os.path.join(LOCK_DIR, f"{mid}.sock")
            p = subprocess.Popen(self.wrap(f"dl{n}", [sys.executable, "-m", "rce.tools.delayline", m_a, m_b,
                                                        "--control", control]),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            self._delay_lines.append(p)
            if p.stdout.readline().strip() != "ready":
                p.kill()
                raise RuntimeError(f"delay line of link {n} did not start: {p.stderr.read()[-1000:]}")
        link = Link(fa, fb, a_dev, b_dev, f"10.{self.subnet}.{n}.1", f"10.{self.subnet}.{n}.2", control)
        for ns, dev, addr in ((fa, a_dev, link.a_ip), (fb, b_dev, link.b_ip)):
            self.ip(*self._in(ns), "addr", "add", f"{addr}/30", "dev", dev)
            self.ip(*self._in(ns), "link", "set", dev, "up")
        self.links.append(link)
        return link

    def _veth(self, a_dev: str, a_ns: str | None, b_dev: str, b_ns: str | None) -> None:
        """A veth pair ``a_dev`` (in ``a_ns``, None: root) <-> ``b_dev`` (in ``b_ns``)."""
        self.ip("link", "add", a_dev, "type", "veth", "peer", "name", b_dev)
        for dev, ns in ((b_dev, b_ns), (a_dev, a_ns)):
            if ns is not None:
                self.ip("link", "set", dev, "netns", ns)

    def set_delay(self, link: Link, ms: float) -> dict:
        """Set the delay line of ``link`` (made with ``delay=True``) to ``ms`` ms each way; returns its
        counters ``{"delay_ms", "forwarded", "dropped", "held"}``. Raises ValueError for a link without
        a delay line, RuntimeError when the line refuses the value."""
        return delayline.request(_control(link), f"delay {ms:g}")

    def delay_stats(self, link: Link) -> dict:
        """The counters of ``link``'s delay line: ``{"delay_ms", "forwarded", "dropped", "held"}``."""
        return delayline.request(_control(link), "stats")

    @staticmethod
    def _in(ns: str | None) -> tuple[str, ...]:
        return ("-n", ns) if ns else ()

    def route(self, ns: str, dst: str, via: str) -> None:
        """In namespace ``ns`` (short name) route ``dst`` (``default`` or a prefix) via ``via``."""
        self.ip("-n", self.full(ns), "route", "replace", dst, "via", via)

    def set_up(self, link: Link, up: bool, side: str = "b") -> None:
        """Bring ``link``'s end on ``side`` ("a" or "b") up or down (down: the other end loses its carrier,
        and what it sends is lost without an error)."""
        ns, dev = (link.a, link.a_dev) if side == "a" else (link.b, link.b_dev)
        self.ip(*self._in(ns), "link", "set", dev, "up" if up else "down")

    def shape(self, link: Link, side: str, rate: str = "10mbit", dscp: bool = False, queue: int = 1000,
              one_segment: bool = False) -> None:
        """Shape what ``link``'s end on ``side`` ("a" or "b") sends to ``rate`` (tc units, e.g. ``10mbit``)
        with HTB (RFC-less, Linux's hierarchical token bucket), a ``queue``-packet FIFO under each class
        (a radio's queue is short: 40 packets are ~0.5 s at 1 Mbit/s); ``one_segment``: one TCP segment
        a packet (``gso_max_segs 1``: HTB lets a segmentation-offload packet of up to 64 kB through at
        once and pays for it after, which no radio does):

        - ``dscp=False``: one class, one FIFO: DSCP marks are ignored;
        - ``dscp=True``: a class per mark by u32 ``tos`` filters: 1:10 EF (0xB8) assured 30 % of ``rate``,
          1:20 the rest (best effort) 50 %, 1:30 CS1 (0x20) 20 %, each borrowing up to ``rate``, EF first.

        Replaces what shaping the end had. Classes: :meth:`class_bytes`."""
        ns, dev = (link.a, link.a_dev) if side == "a" else (link.b, link.b_dev)
        tc = [*(("ip", "netns", "exec", ns) if ns else ()), "tc"]
        subprocess.run([*tc, "qdisc", "del", "dev", dev, "root"], capture_output=True)

        def run(*args: str) -> None:
            subprocess.run([*tc, *args], check=True, capture_output=True, text=True)
        if one_segment:
            subprocess.run([*tc[:-1], "ip", "link", "set", "dev", dev, "gso_max_segs", "1"], check=True,
                           capture_output=True)
        bits = _tc_bits(rate)
        run("qdisc", "add", "dev", dev, "root", "handle", "1:", "htb", "default", "20")
        run("class", "add", "dev", dev, "parent", "1:", "classid", "1:1", "htb", "rate", rate, "ceil", rate)
        classes = ((10, 0.3, 0), (20, 0.5, 1), (30, 0.2, 2)) if dscp else ((20, 1.0, 0),)
        for cid, share, prio in classes:
            run("class", "add", "dev", dev, "parent", "1:1", "classid", f"1:{cid}", "htb", "rate",
                f"{int(bits * share)}bit", "ceil", rate, "prio", str(prio))
            run("qdisc", "add", "dev", dev, "parent", f"1:{cid}", "pfifo", "limit", str(queue))
        if dscp:
            for tos, cid in (("0xb8", 10), ("0x20", 30)):
                run("filter", "add", "dev", dev, "parent", "1:", "protocol", "ip", "prio", "1", "u32", "match",
                    "ip", "tos", tos, "0xfc", "flowid", f"1:{cid}")

    def class_bytes(self, link: Link, side: str) -> dict[str, int]:
        """Bytes each HTB class of ``link``'s end on ``side`` sent (:meth:`shape`): ``{"1:10": n, ...}``."""
        ns, dev = (link.a, link.a_dev) if side == "a" else (link.b, link.b_dev)
        out = subprocess.run([*(("ip", "netns", "exec", ns) if ns else ()), "tc", "-s", "class", "show", "dev", dev],
                             capture_output=True, text=True, check=True).stdout
        return {m.group(1): int(m.group(2)) for m in re.finditer(r"class htb (\S+) .*?\n\s*Sent (\d+) bytes", out)}

    def backlog_argv(self, link: Link, side: str) -> list[str]:
        """The command whose output :func:`qdisc_backlog` reads: ``tc -s qdisc show`` of ``link``'s end on
        ``side`` ("a" or "b"; run it with the event loop's subprocess calls while traffic flows)."""
        ns, dev = (link.a, link.a_dev) if side == "a" else (link.b, link.b_dev)
        return [*(("ip", "netns", "exec", ns) if ns else ()), "tc", "-s", "qdisc", "show", "dev", dev]

    def wrap(self, ns: str, argv: list[str]) -> list[str]:
        """``argv`` run in namespace ``ns`` (short name)."""
        return ["ip", "netns", "exec", self.full(ns), *argv]


def _control(link: Link) -> str:
    """The control socket of ``link``'s delay line; ValueError for a link made without one."""
    if link.control is None:
        raise ValueError(f"link {link.a_dev} <-> {link.b_dev} has no delay line (made without delay=True)")
    return link.control


def qdisc_backlog(tc_output: str) -> int:
    """Bytes waiting in the FIFOs (``pfifo``) of ``tc -s qdisc show`` output (:meth:`NetLab.backlog_argv`)."""
    return sum(int(m.group(1)) for m in re.finditer(r"qdisc pfifo .*?\n.*?\n\s*backlog (\d+)b", tc_output))


def _tc_bits(rate: str) -> int:
    """Bits/s of a tc rate (``10mbit``, ``500kbit``, ``1gbit``, ``8000bit``)."""
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([kmg]?)bit", rate.lower())
    if m is None:
        raise ValueError(f"rate {rate!r}: expected a tc rate in bits, e.g. 10mbit")
    return int(float(m.group(1)) * {"": 1, "k": 1e3, "m": 1e6, "g": 1e9}[m.group(2)])


@dataclass(frozen=True)
class RelayTopology:
    """The relay lab (docs/relays.md): the cloud in the root namespace at :attr:`cloud_ip`; leaders ``l1``
    and ``l2`` with uplinks to it; follower ``f`` with links only to ``l1`` and ``l2``, and a direct
    link to the cloud that is down until :meth:`direct` brings it up."""
    lab: NetLab
    up1: Link           # root <-> l1
    up2: Link           # root <-> l2
    f_l1: Link          # l1 (a) <-> f (b)
    f_l2: Link          # l2 (a) <-> f (b)
    f_cloud: Link       # root (a) <-> f (b)

    @property
    def cloud_ip(self) -> str:
        return self.up1.a_ip

    @classmethod
    def make(cls, lab: NetLab) -> "RelayTopology":
        for name in ("l1", "l2", "f"):
            lab.namespace(name)
        t = cls(lab, lab.link(None, "l1", 1), lab.link(None, "l2", 2), lab.link("l1", "f", 3),
                lab.link("l2", "f", 4), lab.link(None, "f", 5))
        lab.route("l1", "default", t.up1.a_ip)
        lab.route("l2", "default", t.up2.a_ip)
        lab.set_up(t.f_cloud, False)
        return t

    def direct(self, up: bool) -> None:
        """Bring ``f``'s direct link to the cloud up (with its route to the cloud) or down."""
        self.lab.set_up(self.f_cloud, up)
        if up:
            self.lab.ip("-n", self.f_cloud.b, "route", "replace", f"{self.cloud_ip}/32", "via", self.f_cloud.a_ip)
