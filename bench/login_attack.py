"""Real-login latency during a password attack: an attacker's wrong passwords must be
slowed down without slowing the real user's logins (docs/SECURITY.md "Login").

A *real login* is what a robot does: ``GET /?userID&version`` at the master, then the websocket
handshake at the robot endpoint with the right password (the master's scrypt check), then close;
timed from the GET to the open websocket, one after the other from 127.0.0.1. First with no attack
(the baseline), then while ``--attack`` wrong passwords for the same user go, started at ``--rate`` per
s, at most ``--concurrency`` at a time, from ``--addresses`` other loopback addresses (127.0.1.x).
p50/p99 of each and their ratio to the baseline of the same run, for each mode:

- ``guarded``: the master's defaults (login_guard.py: back-off per user and address, bounded scrypt pool);
- ``pool only``: back-off off (thresholds of 10^6), the bounded scrypt pool alone.

Usage::

    .venv/bin/python bench/login_attack.py [--attack 300] [--rate 32] [--concurrency 32] [--addresses 10]
                                           [--baseline 40]

Prints a table and writes ``bench/results/login_attack.json``.
"""
from __future__ import annotations

import argparse
import asyncio
import hashlib
import json
import os
import sys
import time
import urllib.request
from collections import Counter
from pathlib import Path

from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import PASSWORD, RESULTS, USER, console, engine, git_head, percentile, progress, ratio, write_json  # noqa: E402

HANDSHAKE_TIMEOUT = 60.0      # s a handshake may take (an unguarded master under attack is slow, by design here)
NO_THROTTLE = "1000000"       # --login-failures-per-user/-address that never back off ("pool only")
MODES = {"guarded": (), "pool only": ("--login-failures-per-user", NO_THROTTLE,
                                      "--login-failures-per-address", NO_THROTTLE)}


async def robot_login(master_url: str, user: str, password: str, robot: str, addr: str) -> tuple[int, float, float]:
    """One robot login from source address ``addr``: (HTTP status, s in all, s of the GET); 101 when
    the websocket opened."""
    t0 = time.perf_counter()
    url = json.loads(await asyncio.to_thread(_get, f"{master_url}?userID={user}&version=20130902"))["url"]
    got = time.perf_counter() - t0
    digest = hashlib.sha256(password.encode()).hexdigest()
    try:
        ws = await connect(f"{url}?userID={user}&robotID={robot}&password={digest}", local_addr=(addr, 0),
                           open_timeout=HANDSHAKE_TIMEOUT)
    except InvalidStatus as e:
        return e.response.status_code, time.perf_counter() - t0, got
    took = time.perf_counter() - t0
    await ws.close()
    return 101, took, got


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=HANDSHAKE_TIMEOUT) as r:
        return r.read()


async def real_logins(master_url: str, n: int, until: asyncio.Future | None = None) -> list[tuple[float, float]]:
    """``n`` real logins one after the other (with ``until``: at least ``n``, and on until it is done);
    (ms in all, ms of the GET) of each. Raises AssertionError when one is refused."""
    times: list[tuple[float, float]] = []
    while len(times) < n or (until is not None and not until.done()):
        status, took, got = await robot_login(master_url, USER, PASSWORD, "realBot", "127.0.0.1")
        assert status == 101, f"a real login was refused with HTTP {status}"
        times.append((took * 1e3, got * 1e3))
    return times


async def attack(master_url: str, a: argparse.Namespace, bar) -> tuple[Counter, float]:
    """``a.attack`` wrong passwords started at ``a.rate`` per s, at most ``a.concurrency`` at a time,
    round-robin over ``a.addresses`` sources; (statuses, s taken)."""
    sem, statuses = asyncio.Semaphore(a.concurrency), Counter()
    t0 = time.perf_counter()

    async def guess(i: int) -> None:
        async with sem:
            addr = f"127.0.1.{1 + i % a.addresses}"
            status, _, _ = await robot_login(master_url, USER, f"guess{i}", "attackBot", addr)
            statuses[status] += 1
            bar(1)
    guesses = []
    for i in range(a.attack):
        guesses.append(asyncio.ensure_future(guess(i)))
        await asyncio.sleep(1 / a.rate)          # the attack's pace, a timer
    await asyncio.gather(*guesses)
    return statuses, time.perf_counter() - t0


def summary(times: list[tuple[float, float]]) -> dict:
    """p50/p99/max of the logins, and p50 of their GET (no password check: what the machine's load alone costs)."""
    ms = [t for t, _ in times]
    return {"n": len(ms), "p50_ms": percentile(ms, 50), "p99_ms": percentile(ms, 99), "max_ms": max(ms),
            "get_p50_ms": percentile([g for _, g in times], 50)}


async def run_mode(master_url: str, a: argparse.Namespace, prog) -> dict:
    await real_logins(master_url, 3)                                  # warm-up, not measured
    task = prog.add_task("baseline", total=a.baseline)
    base = []
    for _ in range(a.baseline):
        base += await real_logins(master_url, 1)
        prog.advance(task)
    task = prog.add_task("attack", total=a.attack)
    hit = asyncio.ensure_future(attack(master_url, a, lambda k: prog.advance(task, k)))
    during = await real_logins(master_url, a.baseline // 4, until=hit)
    statuses, took = await hit
    b, d = summary(base), summary(during)
    return {"baseline": b, "during_attack": d, "p50_ratio": ratio(d["p50_ms"], b["p50_ms"]),
            "p99_ratio": ratio(d["p99_ms"], b["p99_ms"]), "attack_statuses": dict(statuses),
            "attack_s": took, "attack_rate_per_s": a.attack / took}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--attack", type=int, default=300, help="wrong passwords in the attack (300)")
    p.add_argument("--rate", type=float, default=32.0, help="attack logins started per s (32: the probe's rate)")
    p.add_argument("--concurrency", type=int, default=32, help="attack logins at a time, at most (32)")
    p.add_argument("--addresses", type=int, default=10, help="loopback source addresses of the attack (10)")
    p.add_argument("--baseline", type=int, default=40, help="real logins with no attack (40)")
    p.add_argument("--out", type=Path, default=RESULTS / "login_attack.json")
    a = p.parse_args()
    con = console()
    results = {}
    for mode, args in MODES.items():
        con.print(f"== {mode}")
        with engine(container_hosts=0, master_args=args) as eng, progress(con) as prog:
            results[mode] = asyncio.run(run_mode(eng.master_url, a, prog))
    con.print(f"\nreal-login latency, ms (GET login + websocket handshake with scrypt; {a.attack} wrong passwords, "
              f"{a.rate:g}/s, at most {a.concurrency} at a time, from {a.addresses} addresses)")
    con.print(f"{'mode':<11}{'p50':>8}{'p99':>8}{'p50 att.':>10}{'p99 att.':>10}{'x p50':>7}{'x p99':>7}"
              f"{'GET p50':>9}{'GET att.':>9}{'attack/s':>10}  attack answers")
    for mode, r in results.items():
        b, d = r["baseline"], r["during_attack"]
        con.print(f"{mode:<11}{b['p50_ms']:>8.1f}{b['p99_ms']:>8.1f}{d['p50_ms']:>10.1f}{d['p99_ms']:>10.1f}"
                  f"{r['p50_ratio']:>7.2f}{r['p99_ratio']:>7.2f}{b['get_p50_ms']:>9.1f}{d['get_p50_ms']:>9.1f}"
                  f"{r['attack_rate_per_s']:>10.1f}  "
                  f"{r['attack_statuses']}")
    write_json(a.out, {"attack": a.attack, "rate_per_s": a.rate, "concurrency": a.concurrency, "addresses": a.addresses,
                       "baseline_logins": a.baseline, "cpus": os.cpu_count(), "git": git_head(), "modes": results})
    con.print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
