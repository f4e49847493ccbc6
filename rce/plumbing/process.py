"""What every rce process entry point shares: the ready file, private (secret) files, the run/exit
wrapper, and children that die with their parent (:func:`popen_tied`)."""
from __future__ import annotations

import asyncio
import atexit
import ctypes
import json
import os
import queue
import signal
import subprocess
import sys
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Awaitable, Callable, NoReturn

from rce.plumbing.errors import RCEError
from rce.plumbing.log import setup_logging


def write_ready_file(path: Path | None, data: dict) -> None:
    """Atomically write ``data`` as JSON to ``path`` (tests and launchers wait for it)."""
    if path is None:
        return
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data))
    tmp.replace(path)


def create_private_file(path: Path, text: str) -> bool:
    """Create ``path`` holding ``text``, mode 0600 (its directory created 0700 if missing), unless
    it exists. Atomic: a complete file appears, or another process's, created first, is kept.
    Returns whether this call created it. For secrets: the admin token, the cluster key."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    try:
        os.link(tmp, path)          # fails if the file exists: theirs is kept
        return True
    except FileExistsError:
        return False
    finally:
        os.unlink(tmp)


PR_SET_PDEATHSIG = 1            # prctl(2): the signal a process gets when the thread that forked it ends
SPAWN_QUEUE = 64                # starts waiting for the spawner thread (each caller waits for its own)
_spawner: tuple[int, queue.Queue] | None = None     # (pid, requests) of this process's spawner thread
_spawner_lock = threading.Lock()


def _tie_to(prctl, parent: int, sig: int):
    """A ``preexec_fn``: the child gets ``sig`` when its parent ends (``PR_SET_PDEATHSIG``, prctl(2)); a
    parent already gone by then (the child was re-parented) sends it at once."""
    def preexec() -> None:
        if prctl(PR_SET_PDEATHSIG, sig, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
        if os.getppid() != parent:
            os.kill(os.getpid(), sig)
    return preexec


def _spawn_forever(requests: queue.Queue) -> None:
    prctl = ctypes.CDLL(None, use_errno=True).prctl        # resolved here, never between fork and exec
    while True:
        fut, argv, sig, kw = requests.get()
        if fut.set_running_or_notify_cancel():
            try:
                fut.set_result(subprocess.Popen(argv, preexec_fn=_tie_to(prctl, os.getpid(), sig), **kw))
            except BaseException as e:      # noqa: BLE001 -- the caller's to raise
                fut.set_exception(e)


def popen_tied(argv: list[str], *, pdeathsig: int = signal.SIGTERM, **popen_kw) -> subprocess.Popen:
    """``subprocess.Popen(argv, **popen_kw)`` whose child gets ``pdeathsig`` (default SIGTERM: it stops
    as on ``kill``, its own children with it) when this process ends, even by SIGKILL, so that nothing it
    started is left running (Linux ``PR_SET_PDEATHSIG``, prctl(2), set in the child between fork and exec).
    The kernel sends it when the *thread* that forked the child ends, so every child is forked by one
    daemon thread of this process (started on first use), which ends only with the process: callers on
    short-lived threads (``asyncio.to_thread``) are safe. Raises what Popen raises (OSError, ...)."""
    global _spawner
    with _spawner_lock:
        if _spawner is None or _spawner[0] != os.getpid():      # none yet, or a forked copy's parent's
            _spawner = (os.getpid(), queue.Queue(SPAWN_QUEUE))
            threading.Thread(target=_spawn_forever, args=(_spawner[1],), name="rce-spawner", daemon=True).start()
        requests = _spawner[1]
    fut: Future = Future()
    requests.put((fut, list(argv), int(pdeathsig), popen_kw))
    return fut.result()


def run_loop(coro: Awaitable[Any]) -> Any:
    """``asyncio.run(coro)`` on uvloop when it is installed (libuv's loop: about half the per-hop
    cost of the default loop on every socket this process serves), else the default loop."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


def run(prog: str, amain: Callable[[Any], Awaitable[Any]], args: Any) -> None:
    """Set up logging and run ``amain(args)``, then end the process (:func:`exit_process`) with its
    code (0 unless it returns an int); an :class:`RCEError` or an OS error (a port in use, an
    unreachable master) exits 1 with a one-line reason instead of a traceback."""
    setup_logging()
    try:
        code = run_loop(amain(args))
    except RCEError as e:
        print(f"{prog}: {e}", file=sys.stderr)
        sys.exit(1)
    except OSError as e:
        print(f"{prog}: {e.strerror or e}", file=sys.stderr)
        sys.exit(1)
    exit_process(code if isinstance(code, int) else 0)


def exit_process(code: int) -> NoReturn:
    """Exit ``code`` once the process is done (:func:`exit_now`); while a thread that is not a
    daemon runs, the interpreter's own exit instead (it waits for the thread)."""
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.main_thread()):
        sys.exit(code)
    exit_now(code)


def exit_command(code: int, argv: list[str] | None) -> NoReturn:
    """Exit a command's ``main(argv)`` with ``code``: run as the command (``argv`` None, the process
    its own) through :func:`exit_process`, with no teardown of its modules; called with ``argv`` by
    another program (a test), by ``SystemExit``, which leaves the caller's process alive."""
    if argv is None:
        exit_process(code)
    sys.exit(code)


def exit_now(code: int) -> NoReturn:
    """End the process as the interpreter ends: its atexit functions (logging's flush among them),
    stdout and stderr flushed (stdout's flush failing exits 120, as the interpreter does), then exit
    ``code`` with ``os._exit``: the imported modules are not torn down (~0.1 s of CPU for a process
    with the engine's libraries), and a forked child runs nothing of its parent's."""
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                if stream is not None and not stream.closed:
                    stream.flush()
            except Exception:       # noqa: BLE001 -- the exit code says it, as the interpreter's does
                if stream is sys.stdout:
                    code = 120
        os._exit(code)
