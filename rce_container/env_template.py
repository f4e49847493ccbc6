"""The container task set's warm environment launcher (a fork server, as
:mod:`rce_container.zygote` is for nodes): ``python -m rce_container.env_template FD [PADDING]``.

Every container group runs in an environment process (:mod:`rce_container.environment`). Started
as a fresh interpreter, each spends most of its start importing the engine. The template imports
:mod:`rce_container.environment` once, when the task set starts, builds the message registry
(:func:`rce.messages.default_registry`, the ROS 1 typestore) each environment starts from, and forks
one child per environment; the child runs :func:`rce_container.environment.main` with the environment's
arguments, as ``python -m rce_container.environment ARGS`` would, and shows that command line
(:func:`rce_container.zygote.set_cmdline`). The template holds no secret: an environment gets
its data key from the task set after its hello, never through the template.

Protocol, on the ``SOCK_SEQPACKET`` socket ``FD`` (one JSON object per packet; the task set's
side is :class:`rce_container.env_template_client.EnvTemplate`):

- template -> task set, once: ``{"op": "ready"}``, or ``{"op": "failed", "error": str}`` and exit 1;
- task set -> template: ``{"op": "spawn", "id": N, "args": [str, ...]}``: an environment with
  those arguments; with one descriptor (SCM_RIGHTS), its zygote template's socket
  (:meth:`rce_container.zygote_client.ZygoteTemplate.fork_template`), which the environment
  gets as ``--zygote-template-fd N`` after those arguments;
- template -> task set: ``{"op": "spawned", "id": N, "pid": P}`` (the child already leads its
  own session and process group), or ``{"op": "refused", "id": N, "error": str}``;
- template -> task set: ``{"op": "exit", "id": N, "code": C}`` or ``{..., "signal": S}`` once
  child N has been reaped.

When the task set's end closes, the template exits and leaves its children running: an
environment notices on its own control link that its task set is gone, as it does when it was
started with exec.
"""
from __future__ import annotations

import json
import os
import random
import signal
import socket
import sys
import traceback

from rce.plumbing.process import exit_now
from rce_container.zygote import (HANDLED_SIGNALS, ForkServer, exit_code, reset_signals, send,
                                  set_cmdline)

#: The command line a forked environment shows (``ps``, psutil), before its arguments.
ENV_COMMAND = ["python", "-m", "rce_container.environment"]


def _run_environment(args: list[str], led: int, inherited: list[int]) -> None:
    """In the fresh child: lead a new session (then write a byte on ``led``), and become an
    environment with ``args``; never returns (``os._exit``)."""
    code = 1
    try:
        os.setsid()
        os.write(led, b"1")
        os.close(led)
        for fd in inherited:
            os.close(fd)
        reset_signals()
        random.seed()                  # not the template's sequence, shared by every sibling
        set_cmdline([sys.executable, *ENV_COMMAND[1:], *args])
        sys.argv = [ENV_COMMAND[-1], *args]
        from rce_container import environment
        environment.main(args)
        code = 0
    except SystemExit as e:
        code = exit_code(e)
    except BaseException:              # noqa: BLE001 -- reported as the interpreter would
        traceback.print_exc()
    exit_now(code)


class EnvForkServer(ForkServer):
    """Forks environments on request; ``children``: pid -> request id."""

    FDS = 1

    def __init__(self, sock: socket.socket):
        super().__init__(sock)
        self.children: dict[int, int] = {}

    def handle(self, data: bytes, fds: list[int]) -> None:
        try:
            req = json.loads(data)
        except ValueError:
            req = None
        if not isinstance(req, dict) or req.get("op") != "spawn" or not isinstance(req.get("args"), list) \
                or not all(isinstance(a, str) for a in req["args"]):
            for fd in fds:
                os.close(fd)
            send(self.sock, {"op": "refused", "id": req.get("id") if isinstance(req, dict) else None,
                             "error": "malformed spawn request"})
            return
        args = req["args"] + [a for fd in fds for a in ("--zygote-template-fd", str(fd))]
        try:
            self.fork(req["id"], args)
        finally:
            for fd in fds:
                os.close(fd)

    def fork(self, rid: int, args: list[str]) -> None:
        """Fork environment ``rid`` with ``args``; say ``spawned`` (or ``refused``)."""
        sys.stdout.flush()
        sys.stderr.flush()
        # the child leads its own session and group before the task set learns its pid (it
        # signals the group): it says so on a pipe, which the template waits for
        led_r, led_w = os.pipe()
        signal.pthread_sigmask(signal.SIG_BLOCK, HANDLED_SIGNALS)   # no template handler may run in the child
        try:
            pid = os.fork()
            if pid == 0:
                _run_environment(args, led_w, [led_r, self.sock.fileno(), self.wake_r, self.wake_w])
        except OSError as e:
            os.close(led_r)
            send(self.sock, {"op": "refused", "id": rid, "error": f"fork: {e}"})
            return
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, HANDLED_SIGNALS)
            os.close(led_w)
        try:
            os.read(led_r, 1)          # b"" if it died first: its exit is reported as any other
        finally:
            os.close(led_r)
        self.children[pid] = rid
        send(self.sock, {"op": "spawned", "id": rid, "pid": pid})

    def reap(self) -> None:
        """Report every environment that has exited."""
        for pid, status in self.reaped():
            try:
                send(self.sock, {"op": "exit", "id": self.children.pop(pid), **status})
            except OSError:
                pass                   # the task set is gone; serve() ends at the next read


def main(argv: list[str] | None = None) -> int:
    """``FD [PADDING]``: serve on the socket ``FD`` (see the module doc)."""
    argv = sys.argv[1:] if argv is None else argv
    sock = socket.socket(fileno=int(argv[0]))
    try:
        from rce_container import environment  # noqa: F401 -- the imports every fork starts with
        from rce.messages import default_registry
        default_registry()             # and the message registry (the ROS 1 typestore) each one builds
    except BaseException as e:         # noqa: BLE001 -- reported to the task set, which then execs environments
        send(sock, {"op": "failed", "error": f"{type(e).__name__}: {e}"})
        return 1
    send(sock, {"op": "ready"})
    EnvForkServer(sock).serve()
    return 0


if __name__ == "__main__":
    exit_now(main())
