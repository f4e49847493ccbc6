"""Names in the code base say what a thing is and why, read from the source; nothing is imported or
run.

- No ticket numbers: code, tests, benches, scripts and web pages speak of the product, never of the
  issue that asked for it (an ``issue N`` reference in a .py, .js, .html, .sh, shell-script or
  Makefile file fails the test with its file:line). Markdown and ``docs/`` may tell the history.
- One name, one thing: no class name is defined in two modules of the project's packages (the
  engine's and the examples'), so that a name in a traceback, a log or a review means one class.
"""
from __future__ import annotations

import ast
import os
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SKIP_DIRS = {"node_modules", ".venv", ".git", "docs", "__pycache__", ".pytest_cache"}
CODE_SUFFIXES = {".py", ".js", ".html", ".sh"}
TICKET = re.compile(r"\b[Ii]ssues?\s+#?\d")
PACKAGES = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client", "examples")
# Class names that are one concept in two processes, each the natural public API of its side.
SAME_CONCEPT = {
    "Publisher",      # a rospy-like publisher handle: of a node (rce.node) and of a robot (rce_client)
    "Subscriber",     # a rospy-like subscriber handle: of a node (rce.node) and of a robot (rce_client)
}


def _is_code(path: Path) -> bool:
    """A file whose text is code: by suffix, a Makefile, or a script with a shell shebang."""
    if path.suffix in CODE_SUFFIXES or path.name == "Makefile":
        return True
    if path.suffix:
        return False
    try:
        with path.open("rb") as f:
            first = f.readline(80)
    except OSError:
        return False
    return first.startswith(b"#!") and (b"sh" in first.split(b"/")[-1])


def _code_files(root: Path) -> list[Path]:
    """Every code file under ``root``, outside SKIP_DIRS, sorted."""
    out = []
    for here, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.endswith(".egg-info"))
        out.extend(p for p in (Path(here) / f for f in files) if _is_code(p))
    return sorted(out)


def _ticket_references(root: Path) -> list[str]:
    """``file:line: text`` of every ticket-number reference in the code files under ``root``."""
    found = []
    for path in _code_files(root):
        text = path.read_text(errors="replace")
        for number, line in enumerate(text.splitlines(), 1):
            if TICKET.search(line):
                found.append(f"{path.relative_to(root)}:{number}: {line.strip()[:100]}")
    return found


def test_ticket_finder_finds_references_in_code_only(tmp_path: Path):
    ticket = "Iss" + "ue 12"                    # spelt in two halves so this file does not hold one
    (tmp_path / "a.py").write_text(f'"""{ticket}: direct links."""\n')
    (tmp_path / "b.js").write_text(f"// fine\n// see {ticket.lower()}\n")
    (tmp_path / "run").write_text(f"#!/bin/bash\n# {ticket}\n")
    (tmp_path / "Makefile").write_text("# t" + ticket.lower() + " is a word, not a ticket\n")
    (tmp_path / "notes.md").write_text(f"{ticket} may be told in prose\n")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "x.html").write_text(ticket)
    (tmp_path / "node_modules").mkdir()
    (tmp_path / "node_modules" / "y.js").write_text(ticket)
    assert [f.split(": ")[0] for f in _ticket_references(tmp_path)] == ["a.py:1", "b.js:2", "run:2"]


def test_no_ticket_numbers_in_the_code():
    found = _ticket_references(ROOT)
    assert not found, "code that names a ticket instead of saying what and why:\n" + "\n".join(found)


def _classes(root: Path, packages: tuple[str, ...]) -> dict[str, list[str]]:
    """Class name -> ``file:line`` of each module that defines it (nested classes included)."""
    where: dict[str, list[str]] = defaultdict(list)
    for top in packages:
        for path in sorted((root / top).rglob("*.py")):
            if SKIP_DIRS.intersection(path.relative_to(root).parts):
                continue
            tree = ast.parse(path.read_text(), str(path))
            seen = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.ClassDef) and node.name not in seen:
                    seen.add(node.name)
                    where[node.name].append(f"{path.relative_to(root)}:{node.lineno}")
    return where


def _names_in_two_modules(root: Path, packages: tuple[str, ...]) -> list[str]:
    """``Name: file:line, file:line`` for each class name defined in more than one module."""
    return [f"{name}: {', '.join(places)}" for name, places in sorted(_classes(root, packages).items())
            if len(places) > 1 and name not in SAME_CONCEPT]


def test_class_name_finder_finds_a_name_in_two_modules(tmp_path: Path):
    (tmp_path / "p" / "q").mkdir(parents=True)
    (tmp_path / "p" / "a.py").write_text("class Office:\n    class Inner:\n        pass\n")
    (tmp_path / "p" / "q" / "b.py").write_text("\n\nclass Office:\n    pass\n\n\nclass Office:\n    pass\n")
    (tmp_path / "p" / "c.py").write_text("class Inner:\n    pass\n\n\nclass Publisher:\n    pass\n")
    (tmp_path / "p" / "d.py").write_text("class Publisher:\n    pass\n")
    assert _names_in_two_modules(tmp_path, ("p",)) == ["Inner: p/a.py:2, p/c.py:1",
                                                        "Office: p/a.py:1, p/q/b.py:3"]


def test_no_class_name_in_two_modules():
    found = _names_in_two_modules(ROOT, PACKAGES)
    assert not found, "class names defined in two modules (give each its own name):\n" + "\n".join(found)
