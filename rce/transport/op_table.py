"""The ops of one control link, listed in one place: op name -> the method that serves it, and
the model of its arguments (:mod:`rce.contract`).

The way rosbridge_suite registers its capabilities (one handler per op, all of them listed by
``rosbridge_protocol.py``): a class names each of its handlers where it defines it, with the
model its arguments are parsed into, and its link serves exactly what the table holds::

    ROBOT_OPS = OpTable("master -> robot task set")

    class RobotEndpoint:
        @ROBOT_OPS.op("connect", args=robot.Connect)
        async def _op_connect(self, args: robot.Connect) -> dict: ...

    peer.handlers.update(ROBOT_OPS.handlers(endpoint))

The table parses each incoming op's ``args`` into its model before the handler runs: a peer's
bad op is refused with a :class:`~rce.plumbing.errors.RequestError` naming the link, the op and
the key (:func:`rce.contract.base.parse`), and the handler reads attributes, never ``args[...]``.

Adding an op touches one place, and a method that is not in the table cannot be served
(tests/core/test_structure_ops.py checks that every ``op_*`` method is, that every entry has its
model, and that no link builds its dispatch by hand). An entry may say more about its op:
``unauthenticated`` (served before the peer is admitted, e.g. the bus's ``hello``) or ``relayed``
(passed on to another process; one method serves every relayed op of a table and takes the op
name first). A link whose ops share a context (the peer, the task set it serves) passes it to
:meth:`OpTable.handlers`, and each method takes it first. A table may also be ``sync``: its
methods are plain functions, called through :meth:`OpTable.call` (a sans-I/O state machine's
steps, e.g. the cluster handshake's).
"""
from __future__ import annotations

from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from typing import Any

from rce.contract.base import OpArgs, parse
from rce.plumbing.errors import ProtocolError, RCEError, RequestError

#: What serves one op on a link: ``async def handler(args) -> result`` (:class:`rce.transport.rpc.RpcPeer`).
Handler = Callable[[dict], Awaitable[Any]]


@dataclass(frozen=True)
class Op:
    """One entry: op ``name`` is served by the method ``method`` (an attribute name of the
    serving object), its arguments parsed into ``args`` (None: a table not typed yet, which the
    structure test names). ``unauthenticated``: served before the peer is admitted; ``relayed``:
    passed on to another process, ``method`` called as ``method(name, args)``."""
    name: str
    method: str
    args: type[OpArgs] | None = None
    unauthenticated: bool = False
    relayed: bool = False


class OpTable:
    """The ops of one link (``link`` names it in errors and docs), in registration order.
    ``sync``: the serving methods are plain functions (:meth:`call`), not coroutines
    (:meth:`handlers`); ``error``: what a bad op's arguments raise (:func:`rce.contract.base.parse`)."""

    def __init__(self, link: str, *, sync: bool = False, error: type[RCEError] = RequestError):
        self.link, self.sync, self.error = link, sync, error
        self._ops: dict[str, Op] = {}

    def op(self, name: str, *, args: type[OpArgs] | None = None,
           unauthenticated: bool = False) -> Callable[[Callable], Callable]:
        """Decorator: the method it decorates serves op ``name``, with its arguments parsed into
        ``args``. Raises :class:`ValueError` for an op registered twice, or a model of another op."""
        def register(fn: Callable) -> Callable:
            self._add(Op(name, fn.__name__, args, unauthenticated=unauthenticated))
            return fn
        return register

    def relay(self, *models: type[OpArgs]) -> Callable[[Callable], Callable]:
        """Decorator: the ops of ``models`` (each named by its ``OP``) are relayed, each served by the
        method it decorates, called as ``method(name, args)`` with ``args`` parsed into its model.
        Raises :class:`ValueError` for an op registered twice."""
        def register(fn: Callable) -> Callable:
            for model in models:
                self._add(Op(model.OP, fn.__name__, model, relayed=True))
            return fn
        return register

    def _add(self, op: Op) -> None:
        if op.name in self._ops:
            raise ValueError(f"op {op.name!r} of {self.link} is registered twice")
        if op.args is not None and op.args.OP != op.name:
            raise ValueError(f"op {op.name!r} of {self.link} names {op.args.__name__}, the model of op "
                             f"{op.args.OP!r}")
        self._ops[op.name] = op

    def __iter__(self) -> Iterator[Op]:
        return iter(self._ops.values())

    def __contains__(self, name: object) -> bool:
        return name in self._ops

    def __len__(self) -> int:
        return len(self._ops)

    def relayed(self) -> list[str]:
        """The names of the relayed ops."""
        return [op.name for op in self if op.relayed]

    def parse(self, name: str, args: Any) -> OpArgs | Any:
        """``args`` of op ``name`` as its model (as they are, for an entry without one). Raises
        :class:`ProtocolError` for an op not in the table, the table's ``error`` for bad arguments."""
        op = self._ops.get(name)
        if op is None:
            raise ProtocolError(f"{self.link}: unknown op {name!r}")
        return args if op.args is None else parse(op.args, args, op=name, link=self.link, error=self.error)

    def handlers(self, obj: Any, *, unauthenticated: bool = False, context: Any = None) -> dict[str, Handler]:
        """Op name -> handler bound to ``obj``, for :attr:`rce.transport.rpc.RpcPeer.handlers`: every op, or
        with ``unauthenticated`` only those served before the peer is admitted. Each handler parses
        the op's arguments into its model, then awaits the method; with ``context`` (what one link's
        ops share, e.g. the task set a master's link serves), the method gets it first:
        ``method(context, args)``."""
        if self.sync:
            raise TypeError(f"the ops of {self.link} are served by plain functions: OpTable.call")
        first = () if context is None else (context,)
        return {op.name: self._handler(op, getattr(obj, op.method), first) for op in self
                if op.unauthenticated or not unauthenticated}

    def _handler(self, op: Op, method: Callable, first: tuple) -> Handler:
        if op.relayed:
            first = (*first, op.name)

        async def served(args: dict) -> Any:
            return await method(*first, self.parse(op.name, args))
        return served

    def call(self, obj: Any, name: str, args: Any) -> Any:
        """(a ``sync`` table) Serve op ``name`` with ``args`` on ``obj`` now: parse, call, return
        what the method returns. Raises as :meth:`parse` does, and what the method raises."""
        model = self.parse(name, args)
        return getattr(obj, self._ops[name].method)(model)
