"""The type of an interface (docs/design.md, section 3.5), parsed once: a kind (the prefix) and a side (the suffix).

The wire names an interface type with one string, e.g. ``"PublisherConverter"``, or one of the
RCE alpha client's names for the service-client kinds (``"ServiceConverter"``...).
:meth:`InterfaceType.parse` turns it into one of the twelve :class:`InterfaceType` members, which
say their :attr:`~InterfaceType.kind` and :attr:`~InterfaceType.side`; a member is a ``str`` (its
canonical name), so it goes back on the wire and into records as the string it stands for.
"""
from __future__ import annotations

from enum import StrEnum

from rce.plumbing.errors import ProtocolError, RequestError


class Kind(StrEnum):
    """What an interface does, named on the side where it acts (:mod:`rce.transport.interface`)."""
    SERVICE_CLIENT = "ServiceClient"
    SERVICE_PROVIDER = "ServiceProvider"
    PUBLISHER = "Publisher"
    SUBSCRIBER = "Subscriber"

    @property
    def service(self) -> bool:
        """A service kind (it carries service calls, not topic messages)."""
        return self in (Kind.SERVICE_CLIENT, Kind.SERVICE_PROVIDER)

    @property
    def peer(self) -> Kind:
        """The one kind a connection pairs this one with (Publisher with Subscriber, ServiceClient
        with ServiceProvider)."""
        return _PEERS[self]


_PEERS = {Kind.PUBLISHER: Kind.SUBSCRIBER, Kind.SUBSCRIBER: Kind.PUBLISHER,
          Kind.SERVICE_CLIENT: Kind.SERVICE_PROVIDER, Kind.SERVICE_PROVIDER: Kind.SERVICE_CLIENT}


class Side(StrEnum):
    """Where an interface lives: ``Interface`` on a container's bus; ``Converter`` (JSON) and
    ``Forwarder`` (the serialized message as a binary part) on the robot's side."""
    INTERFACE = "Interface"
    CONVERTER = "Converter"
    FORWARDER = "Forwarder"


#: Names the RCE alpha client used for the service-client kinds.
LEGACY_NAMES = {"ServiceInterface": "ServiceClientInterface",
                "ServiceConverter": "ServiceClientConverter",
                "ServiceForwarder": "ServiceClientForwarder"}


class InterfaceType(StrEnum):
    """One of the twelve interface types: :class:`Kind` x :class:`Side`."""
    kind: Kind
    side: Side

    def __new__(cls, kind: Kind, side: Side) -> InterfaceType:
        member = str.__new__(cls, kind + side)
        member._value_ = kind + side
        member.kind, member.side = kind, side
        return member

    SERVICE_CLIENT_INTERFACE = Kind.SERVICE_CLIENT, Side.INTERFACE
    SERVICE_CLIENT_CONVERTER = Kind.SERVICE_CLIENT, Side.CONVERTER
    SERVICE_CLIENT_FORWARDER = Kind.SERVICE_CLIENT, Side.FORWARDER
    SERVICE_PROVIDER_INTERFACE = Kind.SERVICE_PROVIDER, Side.INTERFACE
    SERVICE_PROVIDER_CONVERTER = Kind.SERVICE_PROVIDER, Side.CONVERTER
    SERVICE_PROVIDER_FORWARDER = Kind.SERVICE_PROVIDER, Side.FORWARDER
    PUBLISHER_INTERFACE = Kind.PUBLISHER, Side.INTERFACE
    PUBLISHER_CONVERTER = Kind.PUBLISHER, Side.CONVERTER
    PUBLISHER_FORWARDER = Kind.PUBLISHER, Side.FORWARDER
    SUBSCRIBER_INTERFACE = Kind.SUBSCRIBER, Side.INTERFACE
    SUBSCRIBER_CONVERTER = Kind.SUBSCRIBER, Side.CONVERTER
    SUBSCRIBER_FORWARDER = Kind.SUBSCRIBER, Side.FORWARDER

    @property
    def robot_side(self) -> bool:
        """A converter or forwarder: it lives in a robot's session, not on a container's bus."""
        return self.side is not Side.INTERFACE

    @classmethod
    def parse(cls, name: object, *, robot_side: bool | None = None) -> InterfaceType:
        """The member for wire name ``name`` (a member, a canonical name, or an RCE alpha name).
        ``robot_side``: True refuses a container-side type, False a robot-side one.

        Raises :class:`ProtocolError` for an unknown type, :class:`RequestError` for one on the
        wrong side."""
        if isinstance(name, InterfaceType):
            itype = name
        else:
            itype = cls._value2member_map_.get(LEGACY_NAMES.get(name, name) if isinstance(name, str) else None)
            if itype is None:
                raise ProtocolError(f"unknown interface type {name!r}: expected one of "
                                    f"{{{', '.join(Kind)}}} x {{{', '.join(Side)}}}")
        if robot_side is True and not itype.robot_side:
            raise RequestError(f"{name} is a container interface, not a robot-side one")
        if robot_side is False and itype.robot_side:
            raise RequestError(f"{name!r} is a robot-side interface type; containers take *Interface types")
        return itype
