"""Every Debian package the suite needs is installed by ``make setup`` (``.ci/system-deps``, which
reads ``.ci/debian-packages``), so a fresh machine passes as this one does.

- Every module the project's code, tests and benchmarks import that is neither in the standard
  library, nor installed in the virtual environment, nor part of this repository must be listed
  in ``.ci/debian-packages`` (``py:MODULE`` on its package's line).
- Every check there holds on this machine: each ``py:`` module imports under Debian's
  ``/usr/bin/python3``, each ``cmd:`` is on PATH, each ``file:`` exists. A failure names the
  Debian package to install or to add.
"""
from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MANIFEST = ROOT / ".ci" / "debian-packages"
SOURCES = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client", "examples", "tests", "bench")
SKIP_DIRS = {"node_modules", "__pycache__", "results"}
DEBIAN_PY = "/usr/bin/python3"


def manifest() -> list[tuple[str, list[str]]]:
    """``(package, [check, ...])`` per line of ``.ci/debian-packages`` (comments and blanks skipped)."""
    out = []
    for line in MANIFEST.read_text().splitlines():
        words = line.split("#", 1)[0].split()
        if words:
            out.append((words[0], words[1:]))
    return out


def _catches_import_error(node: ast.stmt) -> bool:
    """A ``try`` with an ``except ImportError`` (or ``ModuleNotFoundError``) handler."""
    return isinstance(node, ast.Try) and any(
        isinstance(h.type, ast.Name) and h.type.id in ("ImportError", "ModuleNotFoundError")
        or isinstance(h.type, ast.Tuple) and any(getattr(e, "id", "") in ("ImportError", "ModuleNotFoundError")
                                                 for e in h.type.elts)
        for h in node.handlers)


def _statements(body: list[ast.stmt], guarded: bool = False) -> Iterator[tuple[ast.stmt, bool]]:
    """Each statement of ``body`` and of the blocks in it, with whether it lies anywhere inside a
    ``try: ... except ImportError`` (an optional dependency). Imports are statements, so the
    expressions are not walked."""
    for stmt in body:
        yield stmt, guarded
        inner = guarded or _catches_import_error(stmt)
        blocks = [getattr(stmt, f, ()) for f in ("body", "orelse", "finalbody")]
        blocks += [part.body for f in ("handlers", "cases") for part in getattr(stmt, f, ())]
        for block in blocks:
            yield from _statements(block, inner)


def imported_modules() -> dict[str, str]:
    """Top-level module name -> the first file (relative) that imports it unconditionally."""
    found: dict[str, str] = {}
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*.py")):
            if SKIP_DIRS & set(path.parts):
                continue
            for node, guarded in _statements(ast.parse(path.read_bytes(), str(path)).body):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                if guarded:
                    continue
                for name in names:
                    found.setdefault(name.split(".")[0], str(path.relative_to(ROOT)))
    return found


def local_names() -> set[str]:
    """Names that are modules or packages of this repository (test helpers, bench modules, ...)."""
    names = set()
    for path in ROOT.rglob("*"):
        if SKIP_DIRS & set(path.parts) or ".git" in path.parts or ".venv" in path.parts:
            continue
        if path.suffix == ".py":
            names.add(path.stem)
        elif path.is_dir():
            names.add(path.name)
    return names


def test_every_module_outside_the_venv_is_in_a_listed_debian_package():
    listed = {c[3:] for _, checks in manifest() for c in checks if c.startswith("py:")}
    local = local_names()
    missing = {}
    for name, where in sorted(imported_modules().items()):
        if name in sys.stdlib_module_names or name in local or name in listed or name == "__future__":
            continue
        if importlib.util.find_spec(name) is not None:
            continue
        missing[name] = where
    assert not missing, (
        "modules imported but neither in the venv (pyproject.toml) nor listed in .ci/debian-packages: "
        + ", ".join(f"{m} (imported by {w})" for m, w in missing.items())
        + "; add the Debian package that provides each (dpkg -S or apt-file search) with a py: check")


def test_every_listed_debian_package_is_installed():
    problems = []
    for package, checks in manifest():
        for check in checks:
            kind, _, what = check.partition(":")
            if kind == "cmd":
                ok = shutil.which(what) is not None
            elif kind == "file":
                ok = Path(what).exists()
            elif kind == "py":
                ok = Path(DEBIAN_PY).exists() and subprocess.run(
                    [DEBIAN_PY, "-c", f"import {what}"], capture_output=True, timeout=60).returncode == 0
            else:
                raise AssertionError(f".ci/debian-packages: {package}: unknown check {check!r} (cmd:, file:, py:)")
            if not ok:
                problems.append(f"{package} ({check})")
    assert not problems, ("Debian packages missing on this machine: " + ", ".join(problems)
                          + "; `make setup` installs them as root (.ci/system-deps)")


def test_system_deps_reads_the_manifest():
    """The installer reads the manifest this test checks, not a list of its own."""
    text = (ROOT / ".ci" / "system-deps").read_text()
    assert "debian-packages" in text
    assert not any(f"need+=({pkg})" in text for pkg, _ in manifest())
