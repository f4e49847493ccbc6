"""Product code bounds a wait with ``async with asyncio.timeout(t)``, never ``asyncio.wait_for``: on
Python 3.11 ``wait_for`` loses a cancellation that arrives as the awaited thing completes (CPython
gh-86296; 3.12 rebuilt it on ``asyncio.timeout``), so a task cancelled at that moment runs on. The
check reads the source (nothing is imported or run) and names file:line of each call, also through
``import asyncio as aio`` or ``from asyncio import wait_for``. Methods of the same name that are
something else (``asyncio.Condition.wait_for(predicate)``) are not calls of it."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
# the packages pyproject.toml installs (rce_fleet lives in examples/fleet)
PRODUCT = ("rce", "rce_master", "rce_robot", "rce_container", "rce_client", "examples/fleet/rce_fleet")


def wait_for_calls(tree: ast.AST) -> list[int]:
    """The lines of each call of ``asyncio.wait_for`` in ``tree``, however the module was imported."""
    modules = {"asyncio"}       # names bound to the asyncio module
    functions = set()           # names bound to asyncio.wait_for itself
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update(a.asname or a.name for a in node.names if a.name == "asyncio")
        elif isinstance(node, ast.ImportFrom) and node.module in ("asyncio", "asyncio.tasks"):
            functions.update(a.asname or a.name for a in node.names if a.name == "wait_for")
    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f = node.func
        if (isinstance(f, ast.Attribute) and f.attr == "wait_for" and isinstance(f.value, ast.Name)
                and f.value.id in modules) or (isinstance(f, ast.Name) and f.id in functions):
            lines.append(node.lineno)
    return sorted(lines)


def test_the_check_sees_each_form_of_the_call():
    tree = ast.parse("import asyncio\nimport asyncio as aio\nfrom asyncio import wait_for as wf\n"
                     "async def f(cond, fut):\n"
                     "    await asyncio.wait_for(fut, 1)\n"
                     "    await aio.wait_for(fut, 1)\n"
                     "    await wf(fut, 1)\n"
                     "    await cond.wait_for(lambda: True)\n"
                     "    async with asyncio.timeout(1):\n"
                     "        await fut\n")
    assert wait_for_calls(tree) == [5, 6, 7]


def test_no_product_code_calls_asyncio_wait_for():
    found = [f"{p.relative_to(ROOT)}:{line}"
             for top in PRODUCT for p in sorted((ROOT / top).rglob("*.py"))
             for line in wait_for_calls(ast.parse(p.read_text(), str(p)))]
    assert not found, ("asyncio.wait_for may swallow a cancellation on 3.11; bound the wait with "
                       "`async with asyncio.timeout(t):` instead:\n  " + "\n  ".join(found))
