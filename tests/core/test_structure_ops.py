"""The control-plane ops are served from one explicit table per op set (:mod:`rce.transport.op_table`):
every handler method (``op_*``, ``_op_*``) of a serving class is registered in its table, every
table entry names a real method and the model its arguments are parsed into (:mod:`rce.contract`),
every op the container task set relays is one its environments serve, no handler is found by
reflection (``dir()`` scans, ``getattr(self, "_op_" + op)``, ``getattr(self, f"_on_{kind}")``) and no
link builds its dispatch by hand (``peer.handlers[op] = lambda ...``, ``peer.handlers.update({...})``,
a ``handlers()`` that returns a dict of them). Failures name file:line."""
from __future__ import annotations

import ast
import inspect
from pathlib import Path

import pytest

from rce.bus import server as bus_server
from rce.contract.base import OpArgs
from rce.plumbing.errors import RequestError
from rce.node import links as node_links
from rce.node import runtime as node_runtime
from rce.transport import cluster_auth
from rce.transport.op_table import OpTable
from rce_container import environment, host
from rce_master import server as master_server
from rce_robot import endpoint

ROOT = Path(__file__).resolve().parents[2]
ENGINE = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client")
HANDLER_PREFIXES = ("op_", "_op_")

# (serving class, its table): every link of the control plane
OP_SETS = [(bus_server.NodeSession, bus_server.BUS_OPS), (environment.Environment, environment.ENV_OPS),
           (host.ContainerHost, host.HOST_OPS), (host.ContainerHost, host.FROM_ENV_OPS),
           (endpoint.RobotEndpoint, endpoint.ROBOT_OPS), (node_links.DirectLinks, node_links.DIRECT_OPS),
           (node_runtime.Node, node_runtime.NODE_OPS), (cluster_auth.Handshake, cluster_auth.HANDSHAKE),
           (master_server.Master, master_server.MASTER_OPS), (master_server.Master, master_server.ROBOT_SET_OPS),
           (master_server.Master, master_server.HOST_SET_OPS)]


def _where(cls: type) -> tuple[Path, ast.ClassDef]:
    path = Path(inspect.getsourcefile(cls))
    tree = ast.parse(path.read_text(), str(path))
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    return path, node


def unregistered(cls: type, tables: list[OpTable]) -> list[str]:
    """file:line of each handler method of ``cls`` that none of ``tables`` (those it serves) names."""
    path, node = _where(cls)
    served = {op.method for table in tables for op in table}
    links = " or ".join(repr(t.link) for t in tables)
    return [f"{path.relative_to(ROOT)}:{f.lineno} {cls.__name__}.{f.name} is not in {links}'s table"
            for f in node.body if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
            and f.name.startswith(HANDLER_PREFIXES) and f.name not in served]


def dangling(cls: type, table: OpTable) -> list[str]:
    """Each entry of ``table`` whose method is not a method of ``cls`` of the table's kind (a coroutine
    method; a plain one for a ``sync`` table), file:line of the class."""
    path, node = _where(cls)
    kind = "plain" if table.sync else "coroutine"

    def fits(method: object) -> bool:
        return callable(method) and inspect.iscoroutinefunction(method) != table.sync
    return [f"{path.relative_to(ROOT)}:{node.lineno} op {op.name!r} of {table.link!r} names {op.method!r}, "
            f"not a {kind} method of {cls.__name__}"
            for op in table if not fits(getattr(cls, op.method, None))]


def untyped(cls: type, table: OpTable) -> list[str]:
    """Each entry of ``table`` with no model of its arguments (:mod:`rce.contract`), file:line of its method."""
    out = []
    for op in table:
        if op.args is None or not issubclass(op.args, OpArgs):
            fn = inspect.unwrap(getattr(cls, op.method))
            where = f"{Path(inspect.getsourcefile(fn)).relative_to(ROOT)}:{inspect.getsourcelines(fn)[1]}"
            out.append(f"{where} op {op.name!r} of {table.link!r} has no argument model")
    return out


def _op_prefixed(node: ast.AST) -> bool:
    """A name built at run time from an op-handler prefix: ``"_op_" + op``, ``f"op_{op}"``."""
    if isinstance(node, ast.BinOp):
        node = node.left
    elif isinstance(node, ast.JoinedStr) and node.values:
        node = node.values[0]
    return isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith(HANDLER_PREFIXES)


def _built_name(node: ast.AST) -> bool:
    """A name built at run time: ``"_on_" + kind``, ``f"op_{op}"``."""
    return isinstance(node, (ast.BinOp, ast.JoinedStr))


def reflection(path: Path) -> list[str]:
    """file:line of each handler lookup by reflection in ``path``: a ``dir()`` call, a
    ``getattr(obj, <op prefix> + op)`` (or any name built at run time), or a test of a name for an op prefix."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for n in ast.walk(tree):
        if not isinstance(n, ast.Call):
            continue
        f = n.func
        if isinstance(f, ast.Name) and f.id == "dir":
            out.append(f"{path}:{n.lineno} dir() scan")
        elif isinstance(f, ast.Name) and f.id == "getattr" and len(n.args) >= 2 and _built_name(n.args[1]):
            out.append(f"{path}:{n.lineno} getattr of a handler by a built name")
        elif isinstance(f, ast.Attribute) and f.attr == "startswith" and n.args and _op_prefixed(n.args[0]):
            out.append(f"{path}:{n.lineno} a name tested for a handler prefix")
    return out


def _is_handlers(node: ast.AST) -> bool:
    """``<something>.handlers``: a link's dispatch (:attr:`rce.transport.rpc.RpcPeer.handlers`)."""
    return isinstance(node, ast.Attribute) and node.attr == "handlers"


def _from_a_table(node: ast.AST) -> bool:
    """``TABLE.handlers(...)``: the dispatch an :class:`OpTable` builds."""
    return isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "handlers"


def hand_built(path: Path) -> list[str]:
    """file:line of each dispatch built by hand in ``path``: an op put into a link's handlers
    (``x.handlers[op] = ...``), handlers updated with anything but a table's (a dict of lambdas or
    methods, keywords), or a ``handlers`` function that returns a dict of them."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Assign):
            for t in n.targets:
                if isinstance(t, ast.Subscript) and _is_handlers(t.value) and not isinstance(t.slice, ast.Slice):
                    out.append(f"{path}:{n.lineno} an op put into a link's handlers by hand")
        elif isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "update" \
                and _is_handlers(n.func.value):
            if n.keywords or len(n.args) != 1 or not _from_a_table(n.args[0]):
                out.append(f"{path}:{n.lineno} a link's handlers updated by hand")
        elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name == "handlers":
            if any(isinstance(r, ast.Return) and isinstance(r.value, ast.Dict) for r in ast.walk(n)):
                out.append(f"{path}:{n.lineno} a handlers() that returns a dict built by hand")
    return out


# -- the checks find what they look for --------------------------------------------------------------
def test_reflection_finder_finds_the_four_forms(tmp_path: Path):
    f = tmp_path / "m.py"
    f.write_text("class S:\n"
                 "    def a(self):\n"
                 "        return {op[3:]: getattr(self, op) for op in dir(self) if op.startswith('op_')}\n"
                 "    def b(self, op):\n"
                 "        return getattr(self, '_op_' + op), getattr(self, f'op_{op}')\n"
                 "    def c(self, name):\n"
                 "        return getattr(self, name), name.startswith('x')\n"
                 "    def d(self, kind):\n"
                 "        return getattr(self, f'_on_{kind}')\n")
    assert sorted(x.replace(f"{f}:", "") for x in reflection(f)) == [
        "3 a name tested for a handler prefix", "3 dir() scan",
        "5 getattr of a handler by a built name", "5 getattr of a handler by a built name",
        "9 getattr of a handler by a built name"]


def test_hand_built_dispatch_finder_finds_the_three_forms(tmp_path: Path):
    f = tmp_path / "m.py"
    f.write_text("class S:\n"
                 "    def a(self, peer):\n"
                 "        peer.handlers['register'] = lambda args, peer=peer: self.register(peer, args)\n"
                 "        peer.handlers.update({'auth': self.auth, 'lost': lambda args: self.lost(1, args)})\n"
                 "        peer.handlers.update(hello=self.hello)\n"
                 "    def handlers(self):\n"
                 "        return {'direct_link': self.op_direct_link}\n"
                 "    def fine(self, peer, root):\n"
                 "        peer.handlers.update(OPS.handlers(self, context=peer))\n"
                 "        root.handlers[:] = []\n")
    assert sorted(x.replace(f"{f}:", "") for x in hand_built(f)) == [
        "3 an op put into a link's handlers by hand", "4 a link's handlers updated by hand",
        "5 a link's handlers updated by hand", "6 a handlers() that returns a dict built by hand"]


class _Args(OpArgs):
    OP = "kept"
    n: int


def test_registration_checks_find_a_missing_op_a_dangling_entry_and_one_without_a_model():
    table = OpTable("test link")

    class Served:
        @table.op("kept", args=_Args)
        async def op_kept(self, a: _Args) -> None:
            """Registered."""

        @table.op("loose")
        async def op_loose(self, a: dict) -> None:
            """Registered, with no model of its arguments."""

        async def op_forgotten(self, a: dict) -> None:
            """Not registered."""

    table.op("ghost")(lambda self, a: None)          # a table entry that names no method of Served
    missing = unregistered(Served, [table])
    assert len(missing) == 1 and "Served.op_forgotten is not in 'test link'" in missing[0]
    assert missing[0].startswith("tests/core/test_structure_ops.py:")
    assert [x.split(" op ")[1].split(" ")[0] for x in dangling(Served, table)] == ["'ghost'"]
    loose = untyped(Served, _without(table, "ghost"))
    assert len(loose) == 1 and "op 'loose' of 'test link' has no argument model" in loose[0]
    assert loose[0].startswith("tests/core/test_structure_ops.py:")


def _without(table: OpTable, name: str) -> OpTable:
    """A copy of ``table`` without op ``name``."""
    out = OpTable(table.link)
    for op in table:
        if op.name != name:
            out._add(op)
    return out


def test_a_table_refuses_an_op_registered_twice_and_a_model_of_another_op():
    table = OpTable("test link")
    table.op("kept", args=_Args)(lambda self, a: None)

    class Other(OpArgs):
        OP = "other"
    with pytest.raises(ValueError, match="'kept' of test link is registered twice"):
        table.relay(Other, _Args)(lambda self, op, a: None)
    with pytest.raises(ValueError, match="op 'b' of test link names Other, the model of op 'other'"):
        table.op("b", args=Other)(lambda self, a: None)


async def test_a_bad_op_is_refused_naming_its_link_its_op_and_the_key():
    table = OpTable("test link")
    got = []

    class Served:
        @table.op("kept", args=_Args)
        async def op_kept(self, a: _Args) -> int:
            got.append(a)
            return a.n

    serve = table.handlers(Served())["kept"]
    assert await serve({"n": 3, "more": "ignored"}) == 3 and got == [_Args(n=3)]
    with pytest.raises(RequestError, match=r"^test link: op 'kept': n: Field required$"):
        await serve({})
    with pytest.raises(RequestError, match=r"^test link: op 'kept': n: Input should be a valid integer.*, got 'x'$"):
        await serve({"n": "x"})
    with pytest.raises(RequestError, match="its arguments must be an object, got list"):
        await serve([1])
    assert len(got) == 1


# -- the code base -------------------------------------------------------------------------------------
def _tables_of(cls: type) -> list[OpTable]:
    return [t for c, t in OP_SETS if c is cls]


@pytest.mark.parametrize("cls,table", OP_SETS, ids=lambda x: getattr(x, "__name__", getattr(x, "link", "")))
def test_every_handler_is_in_a_table_and_every_entry_is_a_typed_method(cls, table):
    problems = unregistered(cls, _tables_of(cls)) + dangling(cls, table) + untyped(cls, table)
    assert not problems, "\n".join(problems)
    assert len(table) > 0


def test_every_relayed_op_is_served_by_the_environment_with_the_same_model():
    relayed = [op for op in host.HOST_OPS if op.relayed]
    assert relayed, "the container task set relays no op"
    wrong = [op.name for op in relayed if op.name not in environment.ENV_OPS
             or next(e for e in environment.ENV_OPS if e.name == op.name).args is not op.args]
    assert not wrong, f"{Path(host.__file__).relative_to(ROOT)}: relayed but not served so by an environment: {wrong}"


def test_no_handler_is_found_by_reflection():
    found = [x for p in ENGINE for f in sorted((ROOT / p).rglob("*.py")) for x in reflection(f)]
    assert not found, "handlers found by reflection:\n" + "\n".join(
        x.replace(str(ROOT) + "/", "") for x in found)


def test_no_link_builds_its_dispatch_by_hand():
    found = [x for p in ENGINE for f in sorted((ROOT / p).rglob("*.py")) for x in hand_built(f)]
    assert not found, "dispatch built by hand (serve the link's OpTable instead):\n" + "\n".join(
        x.replace(str(ROOT) + "/", "") for x in found)
