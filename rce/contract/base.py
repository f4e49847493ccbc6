"""The base of every op's arguments on an internal control link (:mod:`rce.contract`).

An op is one frozen pydantic model: its fields are the keys of the op's ``args`` on the wire
(:mod:`rce.transport.rpc`), its class attribute :attr:`OpArgs.OP` the op's name. The receiving
table parses the incoming dict into it before a handler runs (:class:`rce.transport.op_table.OpTable`);
the sender builds it and sends :meth:`OpArgs.wire` (:meth:`rce.transport.rpc.RpcPeer.ask`,
:meth:`~rce.transport.rpc.RpcPeer.tell`), so both ends read one definition, as
``@foxglove/ws-protocol``'s ``types.ts`` is imported by its client and its server.

Keys a model does not name are ignored (a newer peer may send more); a value of the wrong type, or
a required key missing, is refused by :func:`parse` with a :class:`~rce.plumbing.errors.RequestError`
naming the link, the op and the key path (pydantic's location), e.g. ``master -> robot task set:
op 'connect': peer_iid: Field required``.
"""
from __future__ import annotations

from typing import Annotated, Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, PlainSerializer, PlainValidator, ValidationError

from rce.interfaces.kind import InterfaceType
from rce.plumbing.errors import RCEError, RequestError
from rce.plumbing.text import key_path, short_repr

#: An interface type as the wire names it (its canonical name, or an RCE alpha one), parsed once
#: (:meth:`InterfaceType.parse`): an unknown one is refused with that method's
#: :class:`~rce.plumbing.errors.ProtocolError` naming it; which side may take it is the receiver's to say.
IType = Annotated[InterfaceType, PlainValidator(InterfaceType.parse), PlainSerializer(str)]


class OpArgs(BaseModel):
    """The arguments of one op (module doc): frozen; unknown keys ignored; ``OP`` names the op."""
    model_config = ConfigDict(frozen=True, extra="ignore")

    #: The op's name on the wire; an :class:`~rce.transport.op_table.OpTable` entry for this model
    #: must serve an op of this name.
    OP: ClassVar[str] = ""

    def wire(self) -> dict[str, Any]:
        """The op's ``args`` as the wire has them: the keys the sender gave (a default it left out
        stays out, so the wire is what a sender of dicts wrote), nested models as objects."""
        return self.model_dump(exclude_unset=True)


A = TypeVar("A", bound=OpArgs)


def parse(model: type[A], args: Any, *, op: str, link: str, error: type[RCEError] = RequestError) -> A:
    """``args`` (an op's arguments as received) as ``model``. Raises ``error`` naming ``link``, ``op``
    and the key path and reason of the first problem (a value is quoted by its first characters)."""
    if not isinstance(args, dict):
        raise error(f"{link}: op {op!r}: its arguments must be an object, got {type(args).__name__}")
    try:
        return model.model_validate(args)
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        where = key_path(tuple(err["loc"])) or "args"
        got = "" if err["type"] == "missing" else f", got {short_repr(err.get('input'))}"
        raise error(f"{link}: op {op!r}: {where}: {err['msg']}{got}") from None
