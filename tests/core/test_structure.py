"""The shape of the code base: no import circle among the project's modules or the bench scripts,
no function over 80 lines in the engine packages, engine tests import nothing from ``examples/``,
the fleet package's parts keep their layers and its sans-I/O cores import no I/O. Read from the
source with :mod:`ast`; nothing is imported or run."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENGINE = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client")
FLEET = ROOT / "examples" / "fleet" / "rce_fleet"
MAX_FUNCTION_LINES = 80


def _modules() -> dict[str, Path]:
    """Module name -> file, for the engine packages and rce_fleet (node-package scripts excluded)."""
    mods: dict[str, Path] = {}
    roots = [(ROOT / p, p) for p in ENGINE] + [(FLEET, "rce_fleet")]
    for base, name in roots:
        for f in base.rglob("*.py"):
            rel = f.relative_to(base)
            if "packages" in rel.parts:          # node programs, run as scripts, not imported
                continue
            parts = [name, *rel.with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = f
    return mods


def _imports(path: Path, module: str, known: set[str]) -> set[str]:
    """The project modules ``module`` imports anywhere: at load time, under ``TYPE_CHECKING``
    and inside functions alike (a circle hidden in a function is still a circle in the design)."""
    tree = ast.parse(path.read_text(), str(path))
    out: set[str] = set()
    pkg = module if path.name == "__init__.py" else module.rpartition(".")[0]

    def add(name: str) -> None:
        while name and name not in known:
            name = name.rpartition(".")[0]
        if name and name != module:
            out.add(name)

    for sub in ast.walk(tree):
        if isinstance(sub, ast.Import):
            for a in sub.names:
                add(a.name)
        elif isinstance(sub, ast.ImportFrom):
            base = sub.module or ""
            if sub.level:
                up = pkg.split(".")[: len(pkg.split(".")) - (sub.level - 1)]
                base = ".".join(up + ([base] if base else []))
            for a in sub.names:
                add(f"{base}.{a.name}" if f"{base}.{a.name}" in known else base)
    return out


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle in ``graph``, as a list of modules, or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        colour[m] = GREY
        stack.append(m)
        for n in sorted(graph.get(m, ())):
            if colour.get(n) == GREY:
                return stack[stack.index(n):] + [n]
            if colour.get(n) == WHITE:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        colour[m] = BLACK
        return None

    for m in sorted(graph):
        if colour[m] == WHITE:
            found = visit(m)
            if found:
                return found
    return None


def test_cycle_finder_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_circle():
    mods = _modules()
    known = set(mods)
    graph = {m: _imports(p, m, known) for m, p in mods.items()}
    # a package's __init__ importing its own submodules is not a circle through the package
    for m in graph:
        graph[m] = {n for n in graph[m] if not m.startswith(n + ".") or mods[n].name != "__init__.py"}
    assert _cycle(graph) is None, f"import circle: {' -> '.join(_cycle(graph))}"


def test_no_import_circle_among_the_bench_scripts():
    """The scripts in ``bench/`` import each other by module name (their directory is on ``sys.path``):
    what two need lives in a third (``common``, ``fleet_wiring``), never in each other."""
    mods = {f.stem: f for f in (ROOT / "bench").glob("*.py")}
    graph = {m: _imports(p, m, set(mods)) for m, p in mods.items()}
    assert _cycle(graph) is None, f"import circle: {' -> '.join(_cycle(graph))}"


def _long_functions(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.lineno + 1
            if n > MAX_FUNCTION_LINES:
                out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    return out


def test_long_function_finder_counts_lines(tmp_path: Path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n" + "    x = 1\n" * MAX_FUNCTION_LINES + "\ndef g():\n    pass\n")
    global ROOT
    old, ROOT = ROOT, tmp_path
    try:
        assert _long_functions(f) == [f"m.py:1 f ({MAX_FUNCTION_LINES + 1} lines)"]
    finally:
        ROOT = old


def test_no_function_over_80_lines_in_the_engine():
    long = [x for p in ENGINE for f in sorted((ROOT / p).rglob("*.py")) for x in _long_functions(f)]
    assert not long, "functions over 80 lines:\n" + "\n".join(long)


ENGINE_TESTS = ("core", "engine", "client", "container", "bench")


def test_engine_tests_import_nothing_from_examples():
    offenders = []
    for f in sorted(f for d in ENGINE_TESTS for f in (ROOT / "tests" / d).rglob("*.py")):
        if f == Path(__file__).resolve():
            continue
        text = f.read_text()
        tree = ast.parse(text, str(f))
        for node in ast.walk(tree):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n == "rce_fleet" or n.startswith("rce_fleet.") for n in names):
                offenders.append(f"{f.relative_to(ROOT)}:{node.lineno}")
        if "examples" in text and "sys.path" in text:
            offenders.append(f"{f.relative_to(ROOT)}: puts examples/ on sys.path")
    assert not offenders, "engine tests importing the fleet example:\n" + "\n".join(offenders)


# rce_fleet's layers (docs/layout.md): each part and the parts of rce_fleet it never imports
LOWER = {"maps", "planning", "lifelong", "sim"}
FLEET_NEVER = {
    "maps": {"planning", "lifelong", "sim", "operations", "nodes", "live", "cli", "configs"},
    **{part: {"operations", "nodes", "live", "cli"} for part in ("planning", "lifelong", "sim")},
    "operations": {"nodes", "live", "cli"},
    "nodes": {"live", "cli"},
    "live": {"cli"},
}
# the fleet's sans-I/O cores: plain classes driven by their callers, so they import no sockets, no event
# loop and no transport
SANS_IO = ("rce_fleet.maps", "rce_fleet.planning", "rce_fleet.lifelong", "rce_fleet.sim",
           "rce_fleet.nodes.global_planner_core", "rce_fleet.nodes.move_client_core", "rce_fleet.nodes.tracking",
           "rce_fleet.operations.places", "rce_fleet.operations.battery", "rce_fleet.operations.tasks_api",
           "rce_fleet.operations.dispatcher", "rce_fleet.operations.api_auth", "rce_fleet.operations.api_models")
IO_MODULES = ("socket", "ssl", "asyncio", "selectors", "http", "urllib.request", "aiohttp", "websockets",
              "picows", "rce.transport", "rce.node", "rce.bus", "rce_client")


def _all_imports(path: Path, module: str) -> set[str]:
    """Every module name ``module`` (at ``path``) imports, relative imports made absolute."""
    tree = ast.parse(path.read_text(), str(path))
    pkg = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for sub in ast.walk(tree):
        if isinstance(sub, ast.Import):
            out.update(a.name for a in sub.names)
        elif isinstance(sub, ast.ImportFrom):
            base = sub.module or ""
            if sub.level:
                up = pkg.split(".")[: len(pkg.split(".")) - (sub.level - 1)]
                base = ".".join(up + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in sub.names)
    return out


def _within(name: str, prefixes) -> str | None:
    return next((p for p in prefixes if name == p or name.startswith(p + ".")), None)


def _layer_offences(mods: dict[str, Path]) -> list[str]:
    out = []
    for m, p in sorted(mods.items()):
        part = m.split(".")[1] if m.startswith("rce_fleet.") else None
        never = {f"rce_fleet.{n}" for n in FLEET_NEVER.get(part, ())}
        out += [f"{m} imports {n}" for n in sorted(_all_imports(p, m)) if _within(n, never)]
    return out


def _io_offences(mods: dict[str, Path]) -> list[str]:
    return [f"{m} imports {n}" for m, p in sorted(mods.items()) if _within(m, SANS_IO)
            for n in sorted(_all_imports(p, m)) if _within(n, IO_MODULES)]


def test_layer_and_io_finders_find_offences(tmp_path: Path):
    core = tmp_path / "tracking.py"
    core.write_text("import asyncio\nfrom ..live.demo import run\n")
    mods = {"rce_fleet.nodes.tracking": core}
    assert _layer_offences(mods) == ["rce_fleet.nodes.tracking imports rce_fleet.live.demo",
                                     "rce_fleet.nodes.tracking imports rce_fleet.live.demo.run"]
    assert _io_offences(mods) == ["rce_fleet.nodes.tracking imports asyncio"]


def test_fleet_parts_keep_their_layers():
    """maps at the bottom; planning, lifelong and sim above it; operations; the container nodes (never
    the demo); live; the CLI on top."""
    mods = _modules()
    assert {m.split(".")[1] for m in mods if m.count(".") >= 2 and m.startswith("rce_fleet.")} >= set(FLEET_NEVER)
    offences = _layer_offences(mods)
    assert not offences, "rce_fleet imports against its layers:\n" + "\n".join(offences)


def test_sans_io_cores_import_no_sockets():
    mods = _modules()
    assert sum(1 for m in mods if _within(m, SANS_IO)) > 40
    offences = _io_offences(mods)
    assert not offences, "sans-I/O cores importing I/O:\n" + "\n".join(offences)


# The engine's layers, bottom to top: a package imports only packages of lower layers (docs/layout.md).
# rce.interfaces (interface kinds, lanes, QoS, class names, graph names) sits below the data plane
# (rce.transport) and the robot protocol (rce.protocol), which both use it. rce.contract (every control
# op as its model) sits above rce.interfaces, whose types its models use, and below rce.transport (whose
# op tables parse into its models) and every package that talks on a link.
ENGINE_LAYERS = (
    ("rce", "rce.plumbing"),
    ("rce.interfaces",),
    ("rce.contract",),
    ("rce.messages", "rce.transport"),
    ("rce.protocol", "rce.bus", "rce.tools"),
    ("rce.foxglove", "rce.node", "rce.ros2"),
    ("rce_master", "rce_robot", "rce_container", "rce_client"),
    ("rce_fleet",),
)


def _engine_package(module: str) -> str:
    parts = module.split(".")
    return f"rce.{parts[1]}" if parts[0] == "rce" and len(parts) > 1 and parts[1] != "__init__" else parts[0]


def _upward_imports(mods: dict[str, Path]) -> list[str]:
    """Each import of a package of the same or a higher layer (another package), as ``module imports name``."""
    rank = {pkg: i for i, layer in enumerate(ENGINE_LAYERS) for pkg in layer}
    known = set(mods)
    out = []
    for m, p in sorted(mods.items()):
        mine = _engine_package(m)
        for n in sorted(_imports(p, m, known)):
            theirs = _engine_package(n)
            if theirs != mine and theirs in rank and mine in rank and rank[theirs] >= rank[mine]:
                out.append(f"{m} ({mine}, layer {rank[mine]}) imports {n} ({theirs}, layer {rank[theirs]})")
    return out


def test_layer_finder_finds_an_upward_import(tmp_path: Path):
    low = tmp_path / "lanes.py"
    low.write_text("from rce.protocol.limits import truncate\n")
    mods = {"rce.interfaces.lanes": low, "rce.protocol.limits": tmp_path / "limits.py"}
    (tmp_path / "limits.py").write_text("")
    rank = {pkg: i for i, layer in enumerate(ENGINE_LAYERS) for pkg in layer}
    assert _upward_imports(mods) == [f"rce.interfaces.lanes (rce.interfaces, layer {rank['rce.interfaces']}) imports "
                                     f"rce.protocol.limits (rce.protocol, layer {rank['rce.protocol']})"]


def test_engine_layers_point_down():
    mods = _modules()
    assert {_engine_package(m) for m in mods} <= {p for layer in ENGINE_LAYERS for p in layer}, \
        "a package of the engine has no layer in ENGINE_LAYERS"
    offences = _upward_imports(mods)
    assert not offences, "imports against the engine's layers:\n" + "\n".join(offences)


def test_no_lazy_module_attributes():
    """No module ``__getattr__`` (PEP 562) stands in for imports: a name is imported from the module that
    defines it, so go-to-definition and the import graph above see it."""
    found = [f"{p.relative_to(ROOT)}:{n.lineno}" for m, p in sorted(_modules().items())
             for n in ast.parse(p.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == "__getattr__"]
    assert not found, "module __getattr__ hooks:\n" + "\n".join(found)
