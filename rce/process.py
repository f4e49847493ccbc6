"""What every rce process entry point shares: the ready file and the run/exit wrapper."""
from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path
from typing import Any, Awaitable, Callable

from rce.errors import RCEError
from rce.log import setup_logging


def write_ready_file(path: Path | None, data: dict) -> None:
    """Atomically write ``data`` as JSON to ``path`` (tests and launchers wait for it)."""
    if path is None:
        return
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)


def run_loop(coro: Awaitable[Any]) -> Any:
    """``asyncio.run(coro)`` on uvloop when it is installed (libuv's loop: about half the per-hop
    cost of the default loop on every socket this process serves), else the default loop."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


def run(prog: str, amain: Callable[[Any], Awaitable[Any]], args: Any) -> None:
    """Set up logging and run ``amain(args)``; an :class:`RCEError` or an OS error (a port in use,
    an unreachable master) exits 1 with a one-line reason instead of a traceback."""
    setup_logging()
    try:
        code = run_loop(amain(args))
    except RCEError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        sys.exit(1)
    except OSError as e:
        print(f"{prog}: {e.strerror or e}", file=sys.stderr)
        sys.exit(1)
    if isinstance(code, int):
        sys.exit(code)
