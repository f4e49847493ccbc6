"""The warm node launcher of a container (a fork server, as Android's zygote or
:mod:`multiprocessing`'s forkserver): ``python -m rce_container.zygote FD [--template]``.

A container's zygote runs *inside* the container's sandbox (its namespaces, cgroup, uid, no
capabilities, a node's minimal environment, :mod:`rce_container.node_env`) with the node
runtime imported once (:data:`PRELOAD`, the message registry and the packages' types), and
forks one child per Python node, which runs the node's script with :func:`runpy.run_path` as
``__main__``. A child inherits exactly what the zygote has, so its sandbox is the one an
exec'd node gets; it only skips the interpreter start and the imports.

The zygote itself comes from the environment's *template* (``--template``, :class:`Template`):
one per environment process, ready before any container with the runtime imported, outside
the sandboxes. For each container it forks a child that enters the container's sandbox
in-process (:mod:`rce_container.sandbox_enter`: cgroup, ``setns``, a second fork for the PID
namespace, ``setsid``, the privilege drop ``setpriv`` does, checked) and serves as that
container's zygote; so a new container's first node waits neither for an interpreter nor
for imports. Without a template (it failed) the zygote is spawned through the sandbox like a
node (``python -m rce_container.zygote FD``) and imports the runtime itself.

An environment's template is itself forked: the container task set starts one template
(exec'd, with a node's minimal environment, so nothing of the host's is in its memory) and,
for each new environment, asks it for a child that serves as that environment's template on
a socket the environment is given (``{"op": "template"}``). Without it (it failed or died) an
environment execs its own template.

Protocol, on the ``SOCK_SEQPACKET`` socket ``FD`` (one JSON object per packet, the
host side is :mod:`rce_container.zygote_client`):

- zygote -> host, once: ``{"op": "ready"}`` (its pid: the message's credentials), or
  ``{"op": "failed", "error": str}`` and exit 1;
- host -> zygote: ``{"op": "spawn", "id": N, "argv": [python, script, arg...], "env": {...},
  "cwd": str}`` with two file descriptors (SCM_RIGHTS, :manpage:`unix(7)`): the write ends of
  the node's stdout and stderr pipes;
- forked node -> host, before it runs anything: ``{"op": "spawned", "id": N}`` (the host learns
  its pid from the message's credentials, ``SO_PASSCRED``), or zygote -> host
  ``{"op": "refused", "id": N, "error": str}``;
- zygote -> host: ``{"op": "exit", "id": N, "code": C}`` or ``{..., "signal": S}`` when child N
  has been reaped, with ``"error": "uncaught TYPE: MESSAGE"`` when the node's script raised
  (its traceback is on its stderr).

A template (``--template``) answers nothing after its ``ready``; it takes, with one descriptor
each (SCM_RIGHTS), ``{"op": "container", "spec": enter_spec}`` (the descriptor: the new
zygote's socket, which then says ``ready`` or ``failed`` as above) and ``{"op": "template"}``
(the descriptor: a new template's socket, which then says ``ready``).

A child leads its own session and process group (as ``setsid`` does for an exec'd node), so
the host stops it as before: SIGTERM to its group, SIGKILL after the grace period. When the
host's end closes (its environment is gone) the zygote SIGKILLs every child's group and exits.
Stdlib and :mod:`rce.plumbing` (the exit a child ends by) only at module level; the node runtime
is imported in :func:`preload`.
"""
from __future__ import annotations

import ctypes
import json
import os
import runpy
import select
import signal
import socket
import sys
import traceback
from typing import NoReturn

from rce.plumbing.process import exit_now

#: Modules every Python node imports (the node runtime and the message codec, numpy included).
PRELOAD = ("rce.node.runtime", "rce.messages", "rce.messages.compiled", "rce.node.package_path")
#: Bytes of the largest request (argv + environment of one node); the host refuses larger ones
#: and then starts that node with exec.
MAX_MESSAGE = 256 * 1024
#: Bytes of a child's "uncaught exception" line the zygote reads and reports.
MAX_ERROR = 1024
#: Signals the zygote handles itself (blocked while it forks, reset in the child).
HANDLED_SIGNALS = {signal.SIGCHLD, signal.SIGTERM, signal.SIGHUP, signal.SIGINT}
#: The :data:`HANDLED_SIGNALS` this interpreter started with ignored (``nohup``, a shell's
#: background job): an exec'd node inherits them ignored (:manpage:`execve(2)` keeps SIG_IGN), so a
#: forked one keeps them ignored too.
INHERITED_IGNORED = frozenset(sig for sig in HANDLED_SIGNALS if signal.getsignal(sig) == signal.SIG_IGN)
#: Bytes of padding on the zygote's command line: room for a forked node's own command line
#: (:func:`set_cmdline`).
CMDLINE_ROOM = 1024
#: Environment variables read when an interpreter starts (not when a fork runs a script): a
#: node whose values differ from the zygote's must be exec'd (host side checks it).
STARTUP_VARS = ("LANG", "LC_ALL", "LC_CTYPE", "PYTHONPATH", "PYTHONUNBUFFERED", "PYTHONHASHSEED",
                "PYTHONDONTWRITEBYTECODE", "PYTHONIOENCODING", "PYTHONUTF8", "PYTHONWARNINGS",
                "PYTHONOPTIMIZE", "PYTHONSAFEPATH", "PYTHONNOUSERSITE")


def set_cmdline(argv: list[str]) -> None:
    """Make ``/proc/self/cmdline`` (what ``ps``, psutil and ``/proc`` readers see) show ``argv``,
    NUL-separated, as an exec'd node's would: it is written over this process's original
    argument strings (``arg_start``..``arg_end`` of :manpage:`proc(5)` ``stat``), which
    :data:`CMDLINE_ROOM` padding made long enough; a longer one is cut, and the rest of the
    area is NULs (readers that split on NUL see empty arguments after the node's). Python keeps
    its own copy of the arguments, so nothing else changes."""
    with open("/proc/self/stat", "rb") as f:
        fields = f.read().rsplit(b")", 1)[1].split()
    start, end = int(fields[45]), int(fields[46])      # fields 48 and 49 (1-based, after "pid (comm)")
    room = end - start - 1                             # the last byte stays NUL
    if room <= 0:
        return
    text = "\0".join(argv).encode(errors="replace")[:room]
    ctypes.memmove(start, text.ljust(room + 1, b"\0"), room + 1)


def preload() -> None:
    """Import the node runtime and load the message types of the packages on the path once,
    so every fork starts with them."""
    import importlib
    for name in PRELOAD:
        importlib.import_module(name)
    from rce.messages import default_registry
    from rce.node import load_types
    load_types(default_registry())


def reset_signals() -> None:
    """In a fresh child of a fork server: the signal dispositions an exec'd interpreter starts
    with (the default, Python's KeyboardInterrupt for SIGINT, or ignored where the server's
    interpreter started with it ignored: :data:`INHERITED_IGNORED`), and the
    :data:`HANDLED_SIGNALS` the server blocked around the fork unblocked (one that arrived
    meanwhile is delivered now, to that action)."""
    for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        if sig in INHERITED_IGNORED:
            signal.signal(sig, signal.SIG_IGN)
        elif sig == signal.SIGINT:
            signal.signal(sig, signal.default_int_handler)
        else:
            signal.signal(sig, signal.SIG_DFL)
    signal.set_wakeup_fd(-1)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, HANDLED_SIGNALS)


def send(sock: socket.socket, msg: dict) -> None:
    """One JSON message, one packet."""
    sock.send(json.dumps(msg).encode())


def exit_code(stop: SystemExit) -> int:
    """What the interpreter would exit with for ``sys.exit(e.code)``."""
    if stop.code is None:
        return 0
    if isinstance(stop.code, int):
        return stop.code & 0xFF
    print(stop.code, file=sys.stderr)
    return 1


def _become_node(req: dict, out: int, err: int, sock: socket.socket, inherited: list[int]) -> None:
    """In the fresh child: the process state an exec'd node would start with (``inherited``:
    the zygote's own descriptors, closed; the child already leads its own session)."""
    sock.close()
    for fd in inherited:
        os.close(fd)
    reset_signals()
    devnull = os.open(os.devnull, os.O_RDONLY)
    for fd, target in ((devnull, 0), (out, 1), (err, 2)):
        os.dup2(fd, target)
        os.close(fd)
    os.chdir(req["cwd"])
    os.environ.clear()
    os.environ.update(req["env"])
    script = req["argv"][1]
    sys.argv = list(req["argv"][1:])
    set_cmdline(req["argv"])
    sys.path[0] = os.path.dirname(os.path.abspath(script))
    if "numpy.random" in sys.modules:      # a fork shares the zygote's generator state: reseed it
        sys.modules["numpy.random"].seed()


def _run_child(req: dict, out: int, err: int, sock: socket.socket, report: int, inherited: list[int]) -> None:
    """Run the node's script as ``__main__``; never returns (``os._exit``)."""
    code = 1
    try:
        _become_node(req, out, err, sock, inherited)
        runpy.run_path(sys.argv[0], run_name="__main__")
        code = 0
    except SystemExit as e:
        code = exit_code(e)
    except BaseException as e:         # noqa: BLE001 -- reported as the interpreter would, plus a line
        traceback.print_exc()
        try:
            os.write(report, f"uncaught {type(e).__name__}: {e}"[:MAX_ERROR].encode(errors="replace"))
        except OSError:
            pass
    exit_now(code)


class ForkServer:
    """The loop of a fork server (a container's zygote, the template, and the environments'
    :mod:`rce_container.env_template`): ``sock`` is the link to the host; each packet (with at
    most :attr:`FDS` descriptors) goes to :meth:`handle`, SIGCHLD to :meth:`reap`; it ends when
    the host's end closes."""

    FDS = 0

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.wake_r, self.wake_w = os.pipe()      # SIGCHLD wakes the select loop (signal.set_wakeup_fd)
        os.set_blocking(self.wake_w, False)

    def serve(self) -> None:
        signal.set_wakeup_fd(self.wake_w)
        signal.signal(signal.SIGCHLD, lambda *_: None)
        while True:
            try:
                ready = select.select([self.sock, self.wake_r], [], [])[0]
            except InterruptedError:
                ready = []
            if self.wake_r in ready:
                os.read(self.wake_r, 4096)
            self.reap()
            if self.sock in ready:
                data, fds, _, _ = socket.recv_fds(self.sock, MAX_MESSAGE, self.FDS)
                if not data:
                    return
                self.handle(data, fds)

    def reap(self) -> None:
        raise NotImplementedError

    def reaped(self):
        """Reap the children of ours (the keys of ``self.children``) that have exited: yields
        ``(pid, {"code": C})`` or ``(pid, {"signal": S})`` for each; others are reaped and skipped."""
        while self.children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            if pid in self.children:
                yield pid, ({"signal": os.WTERMSIG(status)} if os.WIFSIGNALED(status)
                            else {"code": os.waitstatus_to_exitcode(status)})

    def handle(self, data: bytes, fds: list[int]) -> None:
        raise NotImplementedError


class Zygote(ForkServer):
    """The fork server of one container: ``sock`` its link to the host; ``children``: pid ->
    (request id, read end of the child's error pipe)."""

    FDS = 2

    def __init__(self, sock: socket.socket):
        super().__init__(sock)
        self.children: dict[int, tuple[int, int]] = {}

    def spawn(self, req: dict, fds: list[int]) -> None:
        if req.get("op") != "spawn" or len(fds) != 2 or not isinstance(req.get("argv"), list) \
                or len(req["argv"]) < 2 or not isinstance(req.get("env"), dict):
            for fd in fds:
                os.close(fd)
            send(self.sock, {"op": "refused", "id": req.get("id"), "error": "malformed spawn request"})
            return
        r, w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        # no signal may run the zygote's handlers in the child before it has reset them
        signal.pthread_sigmask(signal.SIG_BLOCK, HANDLED_SIGNALS)
        pid = os.fork()
        if pid == 0:
            # its own session and group before the host learns its pid: the host's SIGTERM goes
            # to that group, and one sent before a later setsid would reach no one
            os.setsid()
            os.close(r)
            send(self.sock, {"op": "spawned", "id": req["id"]})     # from the node: its credentials give its pid
            _run_child(req, fds[0], fds[1], self.sock, w,
                       [self.wake_r, self.wake_w, *(er for _, er in self.children.values())])
        signal.pthread_sigmask(signal.SIG_UNBLOCK, HANDLED_SIGNALS)
        os.close(w)
        os.set_blocking(r, False)
        for fd in fds:
            os.close(fd)
        self.children[pid] = (req["id"], r)

    def reap(self) -> None:
        """Report every child that has exited."""
        for pid, status in self.reaped():
            rid, r = self.children.pop(pid)
            msg: dict = {"op": "exit", "id": rid, **status}
            try:
                error = os.read(r, MAX_ERROR)
            except OSError:
                error = b""
            os.close(r)
            if error:
                msg["error"] = error.decode(errors="replace")
            send(self.sock, msg)

    def serve(self) -> None:
        """Answer spawn requests and report exits until the host's end closes."""
        signal.signal(signal.SIGTERM, self._terminated)
        super().serve()

    def handle(self, data: bytes, fds: list[int]) -> None:
        try:
            req = json.loads(data)
        except ValueError:
            req = {}
        self.spawn(req if isinstance(req, dict) else {}, fds)

    def _terminated(self, *_) -> None:
        self.kill_children()
        os._exit(0)

    def kill_children(self) -> None:
        for pid in self.children:
            try:
                os.killpg(pid, signal.SIGKILL)
            except OSError:
                pass


def _serve_container(sock: socket.socket) -> None:
    """Say ``ready`` and serve the container's spawn requests until its end closes."""
    send(sock, {"op": "ready"})
    zygote = Zygote(sock)
    try:
        zygote.serve()
    finally:
        zygote.kill_children()


def _become_zygote(req: dict, fd: int, inherited: list[int]) -> None:
    """In a child of the template: enter the container's sandbox (:mod:`rce_container.sandbox_enter`),
    fork once more (the PID namespace applies to children), and serve as the container's
    zygote; a failure is ``{"op": "failed", "error": str}``. Never returns."""
    from rce_container import sandbox_enter
    code = 1
    try:
        for x in inherited:
            os.close(x)
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        sock = socket.socket(fileno=fd)
        try:
            sandbox_enter.join(req["spec"])
            if os.fork():
                os._exit(0)             # the zygote is reaped by the container's init
            sandbox_enter.drop(req["spec"])
        except (OSError, KeyError, TypeError) as e:
            send(sock, {"op": "failed", "error": f"cannot enter the container's sandbox: {e}"})
            os._exit(1)
        _serve_container(sock)
        code = 0
    finally:
        os._exit(code)


def _become_template(fd: int, inherited: list[int]) -> NoReturn:
    """In a child of a template: lead a session of its own and serve as a new template on the
    socket ``fd`` (an environment's); never returns."""
    code = 1
    try:
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for x in inherited:
            os.close(x)
        os.setsid()
        set_cmdline([sys.executable, "-m", "rce_container.zygote", str(fd), "--template"])
        sock = socket.socket(fileno=fd)
        send(sock, {"op": "ready"})
        Template(sock).serve()
        code = 0
    finally:
        os._exit(code)


class Template(ForkServer):
    """The warm template (``--template``): the container task set's, and one per environment
    process (forked from the task set's), outside every sandbox (as root in the namespaced
    case, with a node's minimal environment and nothing else). For ``{"op": "container",
    "spec": enter_spec}`` with one descriptor (the container's end of a new zygote socket) it
    forks a child that enters that container's sandbox, drops its privileges, and serves as its
    zygote on that socket (:func:`_become_zygote`); for ``{"op": "template"}`` with one
    descriptor, a child that serves as a template on it (:func:`_become_template`). It never
    runs node code and never sees a container's bus token (nodes get their environment with
    each spawn request, from the host) nor anything of the host's environment (it was exec'd
    with a node's), so no secret is in the memory the next zygote or template is copied from."""

    FDS = 1

    def reap(self) -> None:
        """Reap the first children of forks (they exit at once; the zygotes are their children)."""
        try:
            while os.waitpid(-1, os.WNOHANG)[0] > 0:
                pass
        except ChildProcessError:
            pass

    def handle(self, data: bytes, fds: list[int]) -> None:
        try:
            req = json.loads(data)
        except ValueError:
            req = None
        if len(fds) != 1 or not isinstance(req, dict) or req.get("op") not in ("container", "template"):
            for fd in fds:
                os.close(fd)            # the host sees its zygote (or template) socket close
            return
        sys.stdout.flush()
        sys.stderr.flush()
        if os.fork() == 0:
            inherited = [self.sock.fileno(), self.wake_r, self.wake_w]
            if req["op"] == "template":
                _become_template(fds[0], inherited)
            _become_zygote(req, fds[0], inherited)
        os.close(fds[0])


def main(argv: list[str] | None = None) -> int:
    """``FD [--template] [PADDING]``: serve on the socket ``FD`` (see the module doc)."""
    argv = sys.argv[1:] if argv is None else argv
    sock = socket.socket(fileno=int(argv[0]))
    try:
        preload()
    except BaseException as e:         # noqa: BLE001 -- reported to the host, which then execs nodes
        send(sock, {"op": "failed", "error": f"{type(e).__name__}: {e}"})
        return 1
    if "--template" in argv[1:]:
        send(sock, {"op": "ready"})
        Template(sock).serve()
    else:
        _serve_container(sock)
    return 0


if __name__ == "__main__":
    exit_now(main())
