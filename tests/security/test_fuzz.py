"""A fuzzing test: an attacker robot of one user throws a few thousand frames
made by hypothesis at a real rce-robot endpoint (text and binary, valid-ish requests and garbage,
deep nesting, huge numbers, lone surrogates, binary parts and references to them, and at the end
a text frame that is not UTF-8), while two victim robots of another user echo through their
containers. Every echo must arrive, in order; rce-robot (and every engine process) must survive;
the attacker gets ERs and its session is still served. rce-robot's RSS before and after is printed.

Hypothesis runs the examples (batches of frames) synchronously; the robots' websockets live in an
asyncio loop on a thread of their own, so they stay open across examples. Derandomized: the same
frames every run."""
from __future__ import annotations

import asyncio
import json
import threading
from collections import Counter

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed

from rce.tools.launch import start_engine
from security.hostile import Echoer, echo_ready, rss, still_served
from wsclient import RawRobot

MiB = 1024 * 1024
EXAMPLES = 500              # batches of 1-20 frames (hypothesis favours short lists): about 3,000 frames
IDS = [f"{i:032x}" for i in range(6)]          # the part ids references and binary frames share
TAGS = ["c", "fz", "req", "resp", "victim1", "victim2", "fuzzer", "", "x/y", "a" * 300, "fuzzer/req"]
TYPES = ["CC", "DC", "CN", "CX", "DM", "ST", "ER", "AK", "XX", ""]

# -- the frames ---------------------------------------------------------------------------------------
leaf = (st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=40)
        | st.sampled_from(IDS + TAGS))
key = st.text(max_size=8) | st.sampled_from(["msg*", "data*", "msg", "iTag", "type", "containerTag", "nodeTag",
                                              "endpointTag", "interfaceTag", "interfaceType", "className"])
value = st.recursive(leaf, lambda c: st.lists(c, max_size=4) | st.dictionaries(key, c, max_size=4), max_leaves=12)
ref = st.sampled_from(IDS) | st.text("0123456789abcdefXY", min_size=30, max_size=34)
dm = st.fixed_dictionaries({"iTag": st.sampled_from(TAGS), "type": st.sampled_from(["std_msgs/String", "x/Y", ""])},
                           optional={"msgID": st.text(max_size=4) | st.integers(), "msg": value,
                                     "msg*": ref | st.lists(ref, max_size=3)})
component = st.fixed_dictionaries({}, optional={k: st.sampled_from(TAGS) | leaf for k in
                                                ("containerTag", "nodeTag", "pkg", "exe", "endpointTag",
                                                 "interfaceTag", "interfaceType", "className", "name", "value")})
cn = st.dictionaries(st.sampled_from(["addNodes", "removeNodes", "setParam", "deleteParam", "addInterfaces",
                                      "removeInterfaces", "resizeContainer", "bogus"]),
                     st.lists(component | value, max_size=3), max_size=3)
cx = st.dictionaries(st.sampled_from(["connect", "disconnect"]),
                     st.lists(st.fixed_dictionaries({"tagA": st.sampled_from(TAGS), "tagB": st.sampled_from(TAGS)}),
                              max_size=2), max_size=2)
message = st.builds(lambda t, d: json.dumps({"type": t, "data": d}), st.sampled_from(TYPES),
                    dm | cn | cx | value | st.fixed_dictionaries({"containerTag": st.sampled_from(TAGS) | leaf}))
deep = st.integers(50, 3000).map(lambda n: '{"type": "DM", "data": ' + "[" * n + "]" * n + "}")
huge_number = st.integers(300, 20_000).map(
    lambda n: '{"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msg": {"data": ' + "9" * n + "}}}")
odd_json = st.sampled_from(['{"type": "DM", "data": {"iTag": "\\ud800", "type": "x", "msg": {}}}',
                            '{"type": "CC", "data": {"containerTag": "\\udfff"}}', "NaN", "[1e999]",
                            '{"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msg": 1e999}}',
                            '{"a": ' * 200, "}" * 200, '"' + "\\" * 101])
text = message | st.text(max_size=200) | deep | huge_number | odd_json
binary = (st.builds(lambda i, p: i.encode() + p, st.sampled_from(IDS), st.binary(max_size=2048))
          | st.binary(max_size=64)
          | st.integers(1, 16).map(lambda k: IDS[k % len(IDS)].encode() + b"z" * (k * 16 * 1024))
          | st.builds(lambda p: b"\xff\xfe" + b"0" * 30 + p, st.binary(max_size=16)))
frames = st.lists(text | binary, min_size=1, max_size=20)


class Loop:
    """An asyncio loop on a thread of its own: :meth:`run` runs a coroutine there and waits for it."""

    def __init__(self):
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="fuzz-loop", daemon=True)
        self.thread.start()

    def run(self, coro, timeout: float = 120.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


class Attacker:
    """The attacker robot: sends frames, and a reader counts what comes back (it reads all along)."""

    def __init__(self, r: RawRobot):
        self.r, self.got, self.sent = r, Counter(), 0
        self.closed: str | None = None
        self._reader = asyncio.ensure_future(self._read())

    async def _read(self) -> None:
        try:
            async for m in self.r.ws:
                self.got[json.loads(m).get("type") if isinstance(m, str) else "binary"] += 1
        except ConnectionClosed as e:
            self.closed = str(e)

    async def throw(self, batch: list[str | bytes]) -> None:
        for f in batch:
            await self.r.ws.send(f)
            self.sent += 1

    async def served(self) -> None:
        """The session still answers requests (the reader stops to take the answer)."""
        self._reader.cancel()
        await asyncio.gather(self._reader, return_exceptions=True)
        await still_served(self.r, "fuzzdone")


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    # small quotas: the attacker's CCs and addNodes cannot fill the host with processes
    e = start_engine(tmp_path_factory.mktemp("fuzz"), master_args=("--max-containers", "2", "--max-nodes", "2"),
                     robot_args=("--expiry", "5"))
    e.admin("/api/users", {"name": "fuzzer", "password": "fuzzer"})
    yield e
    e.stop()


def test_fuzzed_frames_get_ers_and_leave_other_users_undisturbed(eng):
    loop, pid = Loop(), eng.robot_ready[0]["pid"]
    robots = [RawRobot(eng.master_url, n) for n in ("victim1", "victim2")] + \
        [RawRobot(eng.master_url, "fuzzer", user="fuzzer", password="fuzzer")]

    async def setup():
        for r in robots:
            await r.__aenter__()
        await asyncio.gather(echo_ready(robots[0], "v1C"), echo_ready(robots[1], "v2C"))
        return [Echoer(r).start() for r in robots[:2]], Attacker(robots[2])

    try:
        echoers, attacker = loop.run(setup())
        rss_before = rss(pid)

        @settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
        @given(frames)
        def throw(batch):
            loop.run(attacker.throw(batch))
        throw()
        rss_after = rss(pid)

        async def finish():
            await attacker.served()
            await robots[2].ws.send(b"\xff\xfe not UTF-8", text=True)     # the protocol library closes it (1007)
            await robots[2].ws.wait_closed()
            for e in echoers:
                await e.stop()
            async with RawRobot(eng.master_url, "fuzzer2", user="fuzzer", password="fuzzer") as again:
                await again.probe()
            return robots[2].ws.close_code
        close_code = loop.run(finish())
        print(f"\nfuzz: {attacker.sent} frames; attacker got {dict(attacker.got)}; victims' echoes "
              f"{[len(e.rtts) for e in echoers]}, slowest {max(max(e.rtts) for e in echoers):.2f} s; rce-robot RSS "
              f"{rss_before / MiB:.0f} MiB before, {rss_after / MiB:.0f} MiB after")
        assert attacker.closed is None, f"the attacker's session was closed: {attacker.closed}"
        assert attacker.sent >= 2000 and attacker.got["ER"] > 0
        assert close_code == 1007
        assert eng.alive() == [], f"engine processes exited: {eng.alive()}"
        assert rss_after - rss_before < 150 * MiB
    finally:
        for r in robots:
            if r.ws is not None:
                loop.run(r.ws.close())
        loop.close()
