"""The shared session test vectors (tests/vectors/session.json, format in tests/vectors/README.md)
against rce.protocol.session: the ``client`` section (which the browser's rce.js runs too,
tests/web/test_web_vectors.py) on ClientSession, the ``robot`` section on RobotSession.
Frames in, events and frames out; no sockets."""
from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from rce.protocol.frames import DEFAULT_EXPIRY
from rce.protocol.events import Event, as_record
from rce.protocol.session import ClientSession, ResumeOptions, RobotSession, SessionLimits

VECTORS = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "session.json").read_text())


def test_vector_file_shape():
    assert VECTORS["format"] == 1
    names = [v["name"] for v in VECTORS["client"] + VECTORS["robot"]]
    assert len(names) == len(set(names)), "vector names are unique"
    assert len(VECTORS["client"]) >= 20 and len(VECTORS["robot"]) >= 20
    for v in VECTORS["client"] + VECTORS["robot"]:
        assert v["doc"] and v["steps"] and all("expect" in s for s in v["steps"]), v["name"]


def decode(v: Any) -> Any:
    """``{"$bytes": HEX}`` -> bytes, anywhere in a JSON value."""
    if isinstance(v, dict):
        if set(v) == {"$bytes"}:
            return bytes.fromhex(v["$bytes"])
        return {k: decode(x) for k, x in v.items()}
    if isinstance(v, list):
        return [decode(x) for x in v]
    return v


def matches(expected: Any, actual: Any) -> bool:
    """``actual`` fits ``expected`` (README: ``$bytes``, ``$contains``, ``$any``; booleans are not numbers)."""
    if isinstance(expected, dict):
        if set(expected) == {"$any"}:
            return True
        if set(expected) == {"$contains"}:
            return isinstance(actual, str) and expected["$contains"] in actual
        if set(expected) == {"$bytes"}:
            return isinstance(actual, (bytes, bytearray)) and bytes(actual) == bytes.fromhex(expected["$bytes"])
        return (isinstance(actual, dict) and set(actual) == set(expected)
                and all(matches(expected[k], actual[k]) for k in expected))
    if isinstance(expected, list):
        return (isinstance(actual, list) and len(actual) == len(expected)
                and all(matches(e, a) for e, a in zip(expected, actual, strict=True)))
    if isinstance(expected, bool) or isinstance(actual, bool):
        return expected is actual
    if isinstance(expected, (int, float)) and isinstance(actual, (int, float)):
        return expected == actual
    return type(expected) is type(actual) and expected == actual


def outputs(frames: list[str | bytes], events: list[Event]) -> list[dict]:
    out: list[dict] = [{"frame": {"text": json.loads(f)}} if isinstance(f, str) else {"frame": {"binary": f.hex()}}
                       for f in frames]
    return out + [as_record(e) for e in events]


def check(vector: dict, i: int, step: dict, got: list[dict], stats: dict | None = None) -> None:
    """Frames in order and events in order, exactly (README: the order between a step's frames and its
    events is not compared); with ``"stats"``, those counters."""
    where = f"{vector['name']} step {i}: {json.dumps({k: v for k, v in step.items() if k != 'expect'})[:200]}"
    for kind in ("frame", "event"):
        want = [o for o in step["expect"] if kind in o]
        have = [o for o in got if kind in o]
        assert matches(want, have), f"{where}\n  expected {kind}s {want}\n  got {have}"
    for k, v in step.get("stats", {}).items():
        assert stats is not None and stats[k] == v, f"{where}: stats[{k!r}] = {stats and stats[k]}, expected {v}"


def feed(session: ClientSession | RobotSession, step: dict, now: float) -> float:
    """Feed the inputs both sides share; returns the clock."""
    if "now" in step:
        now = step["now"]
    if "recv" in step:
        r = step["recv"]
        if "text" in r:
            session.receive_text(r["text"], now)
        else:
            session.receive_binary(bytes.fromhex(r["binary"]), now)
    elif "tick" in step:
        now = step["tick"]["now"]
        session.tick(now)
    return now


@pytest.mark.asyncio
@pytest.mark.parametrize("vector", VECTORS["client"], ids=[v["name"] for v in VECTORS["client"]])
async def test_client_vector(vector):
    s = ClientSession(**{"expiry": DEFAULT_EXPIRY, **vector.get("options", {})})
    waiters = []          # the shell's side of pending calls and barriers: someone always waits

    async def wait(key):
        try:
            return await s.pending.wait(key, None)
        except Exception as e:
            return e
    now = 0.0
    try:
        for i, step in enumerate(vector["steps"]):
            now = feed(s, step, now)
            if "send" in step:
                s.send(step["send"]["type"], decode(step["send"]["data"]), step.get("ids"))
            elif "call" in step:
                c = step["call"]
                waiters.append(asyncio.ensure_future(wait(s.call(c["iTag"], c["type"], decode(c["msg"]), c["msgID"],
                                                                 step.get("ids")))))
            elif "barrier" in step:
                waiters.append(asyncio.ensure_future(wait(s.barrier(step["barrier"]["token"]))))
            elif "close" in step:
                s.close(step["close"]["reason"])
            elif "detach" in step:
                s.detach(step["detach"]["reason"])
            elif "attach" in step:
                s.attach()
            check(vector, i, step, outputs(s.data_to_send(), s.events_received()))
            await asyncio.sleep(0)          # let waiters take what was settled
    finally:
        for w in waiters:
            w.cancel()
        await asyncio.gather(*waiters, return_exceptions=True)


def feed_robot(s: RobotSession, step: dict) -> None:
    """The robot section's own inputs (README: robot steps)."""
    if "request_done" in step:
        s.request_done(step["request_done"].get("error"))
    elif "interface" in step:
        i = step["interface"]
        s.add_interface(i["iTag"], i["iType"], i["cls"])
    elif "remove_interface" in step:
        s.remove_interface(step["remove_interface"]["iTag"])
    elif "to_robot" in step:
        m = step["to_robot"]
        if m["type"] == "DM":
            d = decode(m["data"])
            s.send_dm(d["iTag"], d["type"], d.get("msgID"), d["msg"], data=m.get("droppable", False))
        elif m["type"] == "ST":
            s.send_status(m["data"])
        else:
            s.send_error(m["data"])
    elif "answer_call" in step:
        s.answer_call(step["answer_call"]["data"], decode(step["answer_call"]["msg"]))
    elif "fail_call" in step:
        s.fail_call(step["fail_call"]["data"], step["fail_call"]["reason"])
    elif "detach" in step:
        s.detach()
    elif "attach" in step:
        s.attach(step["attach"]["ack"])


RESUME_OPTIONS = {"token": "token", "grace": "grace", "resume_buffer": "buffer", "resume_bytes": "bytes",
                  "ack_every": "ack_every", "ack_delay": "ack_delay"}


def session_options(opts: dict) -> dict:
    """A vector's ``options`` (flat, as the JavaScript side reads them) as RobotSession's ``limits``
    and ``resume``; an unknown option is a TypeError."""
    resume = {RESUME_OPTIONS[k]: opts.pop(k) for k in list(opts) if k in RESUME_OPTIONS}
    out = {"limits": SessionLimits(**{k: opts.pop(k) for k in list(opts) if k != "resume"})}
    if opts.pop("resume", False):
        out["resume"] = ResumeOptions(**resume)
    return out


@pytest.mark.parametrize("vector", VECTORS["robot"], ids=[v["name"] for v in VECTORS["robot"]])
def test_robot_vector(vector):
    opts = dict(vector.get("options", {}))
    manual = opts.pop("manual_write", False)
    s = RobotSession(opts.pop("robot", "r1"), **session_options(opts))
    now = 0.0
    for i, step in enumerate(vector["steps"]):
        now = feed(s, step, now)
        feed_robot(s, step)
        if "write" in step:
            frames = s.data_to_send(step["write"].get("messages"))
        else:
            frames = [] if manual else s.data_to_send()
        check(vector, i, step, outputs(frames, s.events_received()), s.stats())
