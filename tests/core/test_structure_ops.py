"""The control-plane ops are served from one explicit table per op set (:mod:`rce.transport.op_table`):
every handler method (``op_*``, ``_op_*``) of a serving class is registered in its table, every
table entry names a real method, every op the container task set relays is one its environments
serve, and no handler is found by reflection (``dir()`` scans, ``getattr(self, "_op_" + op)``).
Failures name file:line."""
from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from rce.bus import server as bus_server
from rce.transport.op_table import OpTable
from rce_container import environment, host
from rce_robot import endpoint

ROOT = Path(__file__).resolve().parents[2]
ENGINE = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client")
HANDLER_PREFIXES = ("op_", "_op_")

# (serving class, its table)
OP_SETS = [(bus_server.NodeSession, bus_server.BUS_OPS), (environment.Environment, environment.ENV_OPS),
           (host.ContainerHost, host.HOST_OPS), (endpoint.RobotEndpoint, endpoint.ROBOT_OPS)]


def _where(cls: type) -> tuple[Path, ast.ClassDef]:
    path = Path(inspect.getsourcefile(cls))
    tree = ast.parse(path.read_text(), str(path))
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    return path, node


def unregistered(cls: type, table: OpTable) -> list[str]:
    """file:line of each handler method of ``cls`` that ``table`` does not name."""
    path, node = _where(cls)
    served = {op.method for op in table}
    return [f"{path.relative_to(ROOT)}:{f.lineno} {cls.__name__}.{f.name} is not in {table.link!r}'s table"
            for f in node.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
            and f.name.startswith(HANDLER_PREFIXES) and f.name not in served]


def dangling(cls: type, table: OpTable) -> list[str]:
    """Each entry of ``table`` whose method is not a coroutine method of ``cls`` (file:line of the class)."""
    path, node = _where(cls)
    return [f"{path.relative_to(ROOT)}:{node.lineno} op {op.name!r} of {table.link!r} names {op.method!r}, "
            f"not a coroutine method of {cls.__name__}"
            for op in table if not inspect.iscoroutinefunction(getattr(cls, op.method, None))]


def _op_prefixed(node: ast.AST) -> bool:
    """A name built at run time from an op-handler prefix: ``"_op_" + op``, ``f"op_{op}"``."""
    if isinstance(node, ast.BinOp):
        node = node.left
    elif isinstance(node, ast.JoinedStr) and node.values:
        node = node.values[0]
    return isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith(HANDLER_PREFIXES)


def reflection(path: Path) -> list[str]:
    """file:line of each handler lookup by reflection in ``path``: a ``dir()`` call, a
    ``getattr(obj, <op prefix> + op)``, or a test of a name for an op prefix."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for n in ast.walk(tree):
        if not isinstance(n, ast.Call):
            continue
        f = n.func
        if isinstance(f, ast.Name) and f.id == "dir":
            out.append(f"{path}:{n.lineno} dir() scan")
        elif isinstance(f, ast.Name) and f.id == "getattr" and len(n.args) >= 2 and _op_prefixed(n.args[1]):
            out.append(f"{path}:{n.lineno} getattr of a handler by a built name")
        elif isinstance(f, ast.Attribute) and f.attr == "startswith" and n.args and _op_prefixed(n.args[0]):
            out.append(f"{path}:{n.lineno} a name tested for a handler prefix")
    return out


# -- the checks find what they look for --------------------------------------------------------------
def test_reflection_finder_finds_the_three_forms(tmp_path: Path):
    f = tmp_path / "m.py"
    f.write_text("class S:\n"
                 "    def a(self):\n"
                 "        return {op[3:]: getattr(self, op) for op in dir(self) if op.startswith('op_')}\n"
                 "    def b(self, op):\n"
                 "        return getattr(self, '_op_' + op), getattr(self, f'op_{op}')\n"
                 "    def c(self, name):\n"
                 "        return getattr(self, name), name.startswith('x')\n")
    assert sorted(x.replace(f"{f}:", "") for x in reflection(f)) == [
        "3 a name tested for a handler prefix", "3 dir() scan",
        "5 getattr of a handler by a built name", "5 getattr of a handler by a built name"]


def test_registration_checks_find_a_missing_op_and_a_dangling_entry():
    table = OpTable("test link")

    class Served:
        @table.op("kept")
        async def op_kept(self, a: dict) -> None:
            """Registered."""

        async def op_forgotten(self, a: dict) -> None:
            """Not registered."""

    table.op("ghost")(lambda self, a: None)          # a table entry that names no method of Served
    missing = unregistered(Served, table)
    assert len(missing) == 1 and "Served.op_forgotten is not in 'test link'" in missing[0]
    assert missing[0].startswith("tests/core/test_structure_ops.py:")
    assert [x.split(" op ")[1].split(" ")[0] for x in dangling(Served, table)] == ["'ghost'"]


def test_a_table_refuses_an_op_registered_twice():
    table = OpTable("test link")
    table.op("a")(lambda self, a: None)
    with pytest.raises(ValueError, match="'a' of test link is registered twice"):
        table.relay("b", "a")(lambda self, op, a: None)


# -- the code base -------------------------------------------------------------------------------------
@pytest.mark.parametrize("cls,table", OP_SETS, ids=lambda x: getattr(x, "__name__", getattr(x, "link", "")))
def test_every_handler_is_in_its_table_and_every_entry_is_a_method(cls, table):
    problems = unregistered(cls, table) + dangling(cls, table)
    assert not problems, "\n".join(problems)
    assert len(table) > 0


def test_every_relayed_op_is_served_by_the_environment():
    relayed = host.HOST_OPS.relayed()
    assert relayed, "the container task set relays no op"
    missing = [op for op in relayed if op not in environment.ENV_OPS]
    assert not missing, f"{Path(host.__file__).relative_to(ROOT)}: relayed but not served by an environment: {missing}"


def test_no_handler_is_found_by_reflection():
    found = [x for p in ENGINE for f in sorted((ROOT / p).rglob("*.py")) for x in reflection(f)]
    assert not found, "handlers found by reflection:\n" + "\n".join(
        x.replace(str(ROOT) + "/", "") for x in found)
