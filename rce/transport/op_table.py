"""The ops of one control link, listed in one place: op name -> the method that serves it.

The way rosbridge_suite registers its capabilities (one handler per op, all of them listed by
``rosbridge_protocol.py``): a class names each of its handlers where it defines it, and its
link serves exactly what the table holds::

    BUS_OPS = OpTable("node -> bus")

    class NodeSession:
        @BUS_OPS.op("advertise")
        async def op_advertise(self, args: dict) -> int: ...

    peer.handlers.update(BUS_OPS.handlers(session))

Adding an op touches one place, and a method that is not in the table cannot be served
(tests/core/test_structure_ops.py checks that every ``op_*`` method is). An entry may say
more about its op: ``unauthenticated`` (served before the peer is admitted, e.g. the bus's
``hello``) or ``relayed`` (passed on, unchanged, to another process; one method serves every
relayed op of a table and takes the op name first).
"""
from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from rce.transport.rpc import Handler


@dataclass(frozen=True)
class Op:
    """One entry: op ``name`` is served by the method ``method`` (an attribute name of the
    serving object). ``unauthenticated``: served before the peer is admitted; ``relayed``:
    passed on to another process, ``method`` called as ``method(name, args)``."""
    name: str
    method: str
    unauthenticated: bool = False
    relayed: bool = False


class OpTable:
    """The ops of one link (``link`` names it in errors and docs), in registration order."""

    def __init__(self, link: str):
        self.link = link
        self._ops: dict[str, Op] = {}

    def op(self, name: str, *, unauthenticated: bool = False) -> Callable[[Callable], Callable]:
        """Decorator: the method it decorates serves op ``name``. Raises :class:`ValueError` for
        an op registered twice."""
        def register(fn: Callable) -> Callable:
            self._add(Op(name, fn.__name__, unauthenticated=unauthenticated))
            return fn
        return register

    def relay(self, *names: str) -> Callable[[Callable], Callable]:
        """Decorator: ops ``names`` are relayed, each served by the method it decorates, called
        as ``method(name, args)``. Raises :class:`ValueError` for an op registered twice."""
        def register(fn: Callable) -> Callable:
            for name in names:
                self._add(Op(name, fn.__name__, relayed=True))
            return fn
        return register

    def _add(self, op: Op) -> None:
        if op.name in self._ops:
            raise ValueError(f"op {op.name!r} of {self.link} is registered twice")
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

    def handlers(self, obj: Any, *, unauthenticated: bool = False) -> dict[str, Handler]:
        """Op name -> handler bound to ``obj``, for :attr:`rce.transport.rpc.RpcPeer.handlers`: every op, or
        with ``unauthenticated`` only those served before the peer is admitted."""
        out: dict[str, Handler] = {}
        for op in self:
            if unauthenticated and not op.unauthenticated:
                continue
            method = getattr(obj, op.method)
            out[op.name] = functools.partial(method, op.name) if op.relayed else method
        return out
