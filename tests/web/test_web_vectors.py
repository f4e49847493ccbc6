"""The shared session vectors (``tests/vectors/session.json``, format in ``tests/vectors/README.md``)
run through rce.js's ``ClientSession`` in Chromium: every vector of the ``client`` section, one test
each, compared with the README's matching rules. The Python ``ClientSession`` runs the same file
(``tests/core/test_session_vectors.py``), so the browser and the Python client cannot drift.

The page is the web directory served on 127.0.0.1 (``web_root``); each vector gets a fresh session
whose binary part ids come from the vector's ``send`` steps. A missing or empty vector file fails."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

VECTORS = Path(__file__).resolve().parents[1] / "vectors" / "session.json"
STEP_KINDS = ("recv", "send", "call", "barrier", "tick", "close", "detach", "attach")

# Runs one vector in the page: returns one entry per step, {"out": [OUT, ...]} with frames and bytes
# in the vectors' JSON form (text frames parsed, binary frames and bytes as hex), or {"raised": text}.
RUN_VECTOR_JS = """async ({vector, stepKinds}) => {
    const m = await import('./rce.js');
    const toHex = (b) => Array.from(b, (x) => x.toString(16).padStart(2, '0')).join('');
    const fromHex = (h) => new Uint8Array((h.match(/../g) || []).map((x) => parseInt(x, 16)));
    const isObj = (v) => v !== null && typeof v === 'object' && !Array.isArray(v);
    const revive = (v) => Array.isArray(v) ? v.map(revive)
        : !isObj(v) ? v
        : Object.keys(v).length === 1 && typeof v.$bytes === 'string' ? fromHex(v.$bytes)
        : Object.fromEntries(Object.entries(v).map(([k, x]) => [k, revive(x)]));
    const plain = (v) => v instanceof Uint8Array ? {$bytes: toHex(v)}
        : Array.isArray(v) ? v.map(plain)
        : isObj(v) ? Object.fromEntries(Object.entries(v).map(([k, x]) => [k, plain(x)])) : v;
    const camel = (k) => k.replace(/_([a-z])/g, (_, c) => c.toUpperCase());
    const ids = [];
    const options = Object.fromEntries(Object.entries(vector.options || {}).map(([k, v]) => [camel(k), v]));
    const results = [];
    try {
        const s = new m.ClientSession({...options, newId: () => {
            if (!ids.length) throw new Error('the step gave fewer ids than the message has binary parts');
            return ids.shift();
        }});
        for (const step of vector.steps) {
            const kind = stepKinds.find((k) => k in step);
            let out;
            if (kind === 'recv') {
                out = 'text' in step.recv ? s.receiveText(step.recv.text, step.now)
                                          : s.receiveBinary(fromHex(step.recv.binary), step.now);
            } else if (kind === 'send') {
                ids.push(...(step.ids || []));
                out = s.send(step.send.type, revive(step.send.data));
            } else if (kind === 'call') {
                const c = step.call;
                out = s.call(c.iTag, c.type, revive(c.msg), c.msgID);
            } else if (kind === 'barrier') out = s.barrier(step.barrier.token);
            else if (kind === 'tick') out = s.tick(step.tick.now);
            else if (kind === 'close') out = s.close(step.close.reason);
            else if (kind === 'detach') out = s.detach(step.detach.reason);
            else if (kind === 'attach') out = s.attach();
            results.push({out: out.map((o) => !o.frame ? plain(o)
                : {frame: 'text' in o.frame ? {text: JSON.parse(o.frame.text)} : {binary: toHex(o.frame.binary)}})});
        }
    } catch (e) {
        results.push({raised: String(e && e.stack || e)});
    }
    return JSON.parse(JSON.stringify(results));
}"""


def _client_vectors() -> list:
    """One pytest param per client vector; a missing, unreadable or empty file is one failing param."""
    try:
        data = json.loads(VECTORS.read_text())
        vectors = data["client"]
        assert data.get("format") == 1, f"format {data.get('format')!r}, expected 1"
        assert isinstance(vectors, list) and vectors, "the client section is empty"
    except (OSError, ValueError, KeyError, TypeError, AssertionError) as e:
        return [pytest.param({"broken": f"{VECTORS}: {type(e).__name__}: {e}"}, id="no-client-vectors")]
    names = [v.get("name") if isinstance(v, dict) else None for v in vectors]
    return [pytest.param(v, id=str(n)) for v, n in zip(vectors, names, strict=True)]


def _match(exp, got, where: str) -> None:
    """Assert ``got`` matches ``exp`` (README): ``$any``, ``$contains`` (text), ``$bytes`` (hex);
    objects key for key, lists item for item, anything else equal and of the same JSON type."""
    if isinstance(exp, dict) and set(exp) == {"$any"}:
        return
    if isinstance(exp, dict) and set(exp) == {"$contains"}:
        assert isinstance(got, str) and exp["$contains"] in got, \
            f"{where}: {got!r} does not contain {exp['$contains']!r}"
    elif isinstance(exp, dict) and set(exp) == {"$bytes"}:
        assert got == {"$bytes": exp["$bytes"].lower()}, f"{where}: expected bytes {exp['$bytes']}, got {got!r}"
    elif isinstance(exp, dict):
        assert isinstance(got, dict) and set(got) == set(exp), f"{where}: expected keys {sorted(exp)}, got {got!r}"
        for k in exp:
            _match(exp[k], got[k], f"{where}.{k}")
    elif isinstance(exp, list):
        assert isinstance(got, list) and len(got) == len(exp), f"{where}: expected {len(exp)} items, got {got!r}"
        for i, (e, g) in enumerate(zip(exp, got, strict=True)):
            _match(e, g, f"{where}[{i}]")
    else:
        same_type = isinstance(got, bool) == isinstance(exp, bool) and type(got) in (type(exp), int, float)
        assert same_type and got == exp, f"{where}: expected {exp!r}, got {got!r}"


def _normalise(out: dict) -> dict:
    """A binary frame's hex compared without regard to case."""
    frame = out.get("frame") if isinstance(out, dict) else None
    if isinstance(frame, dict) and isinstance(frame.get("binary"), str):
        return {**out, "frame": {**frame, "binary": frame["binary"].lower()}}
    return out


@pytest.fixture(scope="module")
def page(browser, web_root):
    """One page for the module (each vector makes its own session); console kept in ``rce_log``."""
    ctx = browser.new_context()
    pg = ctx.new_page()
    pg.rce_log = []
    pg.on("console", lambda m: pg.rce_log.append(f"console.{m.type}: {m.text}"))
    pg.on("pageerror", lambda e: pg.rce_log.append(f"pageerror: {e}"))
    pg.goto(web_root)
    yield pg
    ctx.close()


@pytest.mark.parametrize("vector", _client_vectors())
def test_client_vector(page, vector):
    assert "broken" not in vector, vector.get("broken")
    name = vector.get("name")
    assert isinstance(name, str) and re.fullmatch(r"[\w.-]+", name), f"vector name {name!r}"
    steps = vector.get("steps")
    assert isinstance(steps, list) and steps, f"{name}: no steps"
    for i, step in enumerate(steps):
        kinds = [k for k in STEP_KINDS if k in step]
        assert len(kinds) == 1 and isinstance(step.get("expect"), list), \
            f"{name} step {i}: needs one of {STEP_KINDS} and an expect list, got {step!r}"
    results = page.evaluate(RUN_VECTOR_JS, {"vector": vector, "stepKinds": list(STEP_KINDS)})
    for i, step in enumerate(steps):
        assert i < len(results), f"{name}: the page returned no result for step {i}"
        res = results[i]
        assert "raised" not in res, f"{name} step {i} {json.dumps(step)}: rce.js raised\n{res['raised']}"
        where = f"{name} step {i} ({next(k for k in STEP_KINDS if k in step)})"
        exp = [_normalise(o) for o in step["expect"]]
        assert len(res["out"]) == len(exp), \
            f"{where}: expected {len(exp)} outputs, got {len(res['out'])}:\n{json.dumps(res['out'], indent=1)}"
        for j, (e, g) in enumerate(zip(exp, res["out"], strict=True)):
            _match(e, g, f"{where} output {j}")
