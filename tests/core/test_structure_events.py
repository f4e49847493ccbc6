"""Session events are types, not strings (rce.protocol.events): no code dispatches on an event's
name, and each shell's dispatch handles every event its session emits, ending in ``unhandled``.
Failures name the file and line."""
from __future__ import annotations

import ast
from pathlib import Path

from rce.protocol.events import NAMES, ClientEvent, Event, RobotEvent, members

ROOT = Path(__file__).resolve().parents[2]
CODE = ["rce", "rce_master", "rce_robot", "rce_container", "rce_client", "examples/fleet/rce_fleet", "bench",
        "tests"]
EVENT_NAMES = set(NAMES.values())
# shell -> (file, function that dispatches the session's events, the union it must handle)
SHELLS = {"robot endpoint": ("rce_robot/namespace.py", "_on_event", RobotEvent),
          "client library": ("rce_client/connection.py", "_dispatch", ClientEvent)}


def _files() -> list[Path]:
    out = []
    for top in CODE:
        out += [p for p in (ROOT / top).rglob("*.py") if "node_modules" not in p.parts]
    return sorted(out)


def _strings(node: ast.AST) -> set[str]:
    """The string constants ``node`` is or holds (a tuple, list or set of them)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return {node.value}
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return set().union(*(_strings(e) for e in node.elts)) if node.elts else set()
    return set()


def _is_name_attr(node: ast.AST) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "name"


def string_dispatch(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, text) of each compare of an ``.name`` attribute with an event's name (``==``, ``!=``,
    ``in``, ``not in``), and each ``match x.name`` with a case naming an event."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(_is_name_attr(s) for s in sides):
                named = set().union(*(_strings(s) for s in sides)) & EVENT_NAMES
                if named:
                    found.append((node.lineno, f"compares .name with {sorted(named)}"))
        elif isinstance(node, ast.Match) and _is_name_attr(node.subject):
            for case in node.cases:
                named = {n.value.value for n in ast.walk(case.pattern)
                         if isinstance(n, ast.MatchValue) and isinstance(n.value, ast.Constant)} & EVENT_NAMES
                if named:
                    found.append((case.pattern.lineno, f"matches .name against {sorted(named)}"))
    return sorted(found)


def test_no_code_dispatches_on_an_event_name():
    bad = [f"{p.relative_to(ROOT)}:{line}: {text}"
           for p in _files() for line, text in string_dispatch(ast.parse(p.read_text(), str(p)))]
    assert not bad, "dispatch on an event's type (match/isinstance), not on a name string:\n  " + "\n  ".join(bad)


def test_the_check_sees_a_string_dispatch():
    tree = ast.parse('if ev.name == "deliver":\n    pass\nif e.name in ("error", "x"):\n    pass\n'
                     'match ev.name:\n    case "call":\n        pass\nif d.name == "Test":\n    pass\n')
    assert [line for line, _ in string_dispatch(tree)] == [1, 3, 6]


def _function(tree: ast.AST, name: str) -> ast.FunctionDef | None:
    return next((n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
                 and n.name == name), None)


def handled(fn: ast.AST) -> tuple[set[str], bool]:
    """The event classes a dispatch function handles (``case Cls(...)``, ``case A() | B()``,
    ``isinstance(x, Cls)``), and whether it ends in ``unhandled`` for any other."""
    names: set[str] = set()
    default = False
    for node in ast.walk(fn):
        if isinstance(node, ast.MatchClass) and isinstance(node.cls, ast.Name):
            names.add(node.cls.id)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            if node.func.id == "isinstance" and len(node.args) == 2:
                kinds = node.args[1].elts if isinstance(node.args[1], ast.Tuple) else [node.args[1]]
                names.update(k.id for k in kinds if isinstance(k, ast.Name))
            elif node.func.id == "unhandled":
                default = True
    return names, default


def test_the_check_sees_what_a_dispatch_handles():
    fn = ast.parse("def d(ev):\n    match ev:\n        case Deliver(itag=i) | ServiceCall():\n            pass\n"
                   "        case _:\n            unhandled(ev)\n    if isinstance(ev, (Lagging, CaughtUp)):\n"
                   "        pass\n").body[0]
    assert handled(fn) == ({"Deliver", "ServiceCall", "Lagging", "CaughtUp"}, True)
    assert handled(ast.parse("def d(ev):\n    match ev:\n        case Deliver():\n            pass\n").body[0]) \
        == ({"Deliver"}, False)


def test_each_shell_handles_every_event_of_its_session():
    bad = []
    for shell, (path, func, union) in SHELLS.items():
        tree = ast.parse((ROOT / path).read_text(), path)
        fn = _function(tree, func)
        if fn is None:
            bad.append(f"{path}: no function {func} (the {shell}'s dispatch)")
            continue
        names, default = handled(fn)
        missing = sorted({c.__name__ for c in members(union)} - names)
        if missing:
            bad.append(f"{path}:{fn.lineno} {func}: the {shell} handles no {', '.join(missing)}")
        if not default:
            bad.append(f"{path}:{fn.lineno} {func}: the {shell}'s dispatch does not end in unhandled(event)")
    assert not bad, "\n".join(bad)


def test_every_event_has_its_vector_name():
    assert set(members(Event)) == set(members(RobotEvent)) | set(members(ClientEvent)) == set(NAMES)
    assert len(EVENT_NAMES) == len(NAMES)
