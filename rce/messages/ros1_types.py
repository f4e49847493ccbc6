"""ROS 1 identities of RCE classes, and rospy classes that carry serialized bytes untouched.

A ROS 1 graph (TCPROS, wiki.ros.org/ROS/TCPROS) matches a publisher and a subscriber, or a
service and its client, by type name and MD5 sum; the publisher also sends the full message
definition (``message_definition``, what ``rostopic echo`` and rosbag show). :func:`message_identity`
and :func:`service_identity` give these for a class name ``pkg/Name``:

- from the rospy class when it is importable (``roslib.message.get_message_class`` /
  ``get_service_class``, as rostopic and rosservice find classes: Debian's ``std_msgs``, a robot's
  catkin workspace on ``PYTHONPATH``);
- otherwise from rce's message registry (the rosbags typestore, node packages on
  ``RCE_PACKAGE_PATH`` included): the definition and message MD5 from rosbags'
  ``generate_msgdef``, a service's MD5 from genmsg's ``compute_md5`` (md5 of the request's and
  the response's MD5 texts, as catkin computes it).

When both know a class, the MD5 sums must agree: the robot's graph and the cloud would read the
bytes differently otherwise.

:func:`raw_message_class` and :func:`raw_service_class` make classes in the manner of
``rospy.AnyMsg``: deserializing keeps the buffer (``_buff``), serializing writes it back, so
bytes pass through rospy without decoding, under the real type name and MD5 sum.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from rce.plumbing.errors import ConfigError, MessageError
from rce.messages import MessageRegistry
from rce.messages.debian_ros1 import import_rospy

#: The separator between the parts of a full message definition (genmsg ``compute_full_text``).
DEFINITION_SEPARATOR = "\n" + "=" * 80 + "\n"


@dataclass(frozen=True)
class Ros1Message:
    """A message class as a ROS 1 graph names it: ``type`` ``pkg/Name``, ``md5sum`` (32 hex),
    ``full_text`` (the definition with its embedded ``MSG:`` parts)."""
    type: str
    md5sum: str
    full_text: str


@dataclass(frozen=True)
class Ros1Service:
    """A service class as a ROS 1 graph names it: ``type`` ``pkg/Name``, ``md5sum``, and its
    ``request`` and ``response`` messages (``pkg/NameRequest``, ``pkg/NameResponse``)."""
    type: str
    md5sum: str
    request: Ros1Message
    response: Ros1Message


def ros1_name(cls: str) -> str:
    """``pkg/Name`` for an RCE class name (``/pkg/Name``, ``pkg/msg/Name`` and ``pkg/srv/Name`` too)."""
    parts = [p for p in cls.split("/") if p]
    if len(parts) == 3 and parts[1] in ("msg", "srv"):
        parts.pop(1)
    return "/".join(parts)


def _of_class(cls: Any) -> Ros1Message:
    return Ros1Message(cls._type, cls._md5sum, cls._full_text)


def _of_service_class(cls: Any) -> Ros1Service:
    return Ros1Service(cls._type, cls._md5sum, _of_class(cls._request_class), _of_class(cls._response_class))


def _registry_message(registry: MessageRegistry, store_type: str, name: str) -> Ros1Message:
    text, md5 = registry.store.generate_msgdef(store_type)
    return Ros1Message(name, md5, text)


def _registry_service(registry: MessageRegistry, name: str) -> Ros1Service:
    req_t, resp_t = registry.srv_types(name)
    req = _registry_message(registry, req_t, name + "Request")
    resp = _registry_message(registry, resp_t, name + "Response")
    return Ros1Service(name, service_md5(name, req.full_text, resp.full_text), req, resp)


def message_identity(cls: str, registry: MessageRegistry) -> Ros1Message:
    """The ROS 1 identity of message class ``cls``. Raises :class:`ConfigError` when neither an
    importable rospy class nor the registry knows it, or when the two disagree."""
    return _identity("message", cls, "get_message_class", _of_class,
                     lambda name: _registry_message(registry, registry.msg_type(name), name))


def service_identity(cls: str, registry: MessageRegistry) -> Ros1Service:
    """The ROS 1 identity of service class ``cls``. Raises :class:`ConfigError` when neither an
    importable rospy class nor the registry knows it, or when the two disagree."""
    return _identity("service", cls, "get_service_class", _of_service_class,
                     lambda name: _registry_service(registry, name))


def _identity(what: str, cls: str, lookup: str, of_class: Callable[[Any], Any],
              from_registry: Callable[[str], Any]) -> Any:
    """The rospy class's identity (``roslib.message.<lookup>``), checked against the registry's."""
    import_rospy()
    import roslib.message
    name = ros1_name(cls)
    ros = getattr(roslib.message, lookup)(name)
    try:
        known = from_registry(name)
    except MessageError as e:
        if ros is None:
            raise ConfigError(f"{what} class {name}: no rospy class and {e.message}") from None
        return of_class(ros)
    if ros is None:
        return known
    if ros._md5sum != known.md5sum:
        raise ConfigError(f"{what} class {name}: the ROS 1 class has MD5 {ros._md5sum} but rce's definition has "
                          f"{known.md5sum}; the robot's graph and the cloud would read its bytes differently")
    return of_class(ros)


def service_md5(name: str, request_text: str, response_text: str) -> str:
    """The MD5 sum of service ``name`` (``pkg/Name``) from the full definitions of its request and
    response, computed by genmsg (``genmsg.compute_md5`` of the ``SrvSpec``, the way catkin's
    genpy does for generated classes)."""
    import_rospy()
    import genmsg
    from genmsg.msg_loader import load_msg_from_string
    ctx = genmsg.MsgContext.create_default()
    specs = []
    for part, text in (("Request", request_text), ("Response", response_text)):
        core, *deps = text.split(DEFINITION_SEPARATOR)
        for dep in deps:
            header, _, body = dep.partition("\n")
            dep_type = header.removeprefix("MSG: ").strip()
            ctx.register(dep_type, load_msg_from_string(ctx, body, dep_type))
        specs.append(load_msg_from_string(ctx, core, name + part))
    pkg, short = name.split("/")
    srv = genmsg.SrvSpec(specs[0], specs[1], request_text + "---\n" + response_text, name, short, pkg)
    return genmsg.compute_md5(ctx, srv)


def raw_message_class(ident: Ros1Message) -> type:
    """A ``rospy.AnyMsg`` subclass with ``ident``'s type name, MD5 sum and definition: rospy
    subscribes and publishes it as that type, and its instances hold the serialized bytes
    (``_buff``) untouched. ``cls.wrap(data)`` makes one holding ``data``."""
    rospy = import_rospy()

    def wrap(cls: type, data: bytes) -> Any:
        m = cls()
        m._buff = data
        return m
    return type(f"Raw_{ident.type.replace('/', '_')}", (rospy.AnyMsg,),
                {"_type": ident.type, "_md5sum": ident.md5sum, "_full_text": ident.full_text, "__slots__": (),
                 "wrap": classmethod(wrap)})


def raw_service_class(ident: Ros1Service) -> type:
    """A rospy service class (``_type``, ``_md5sum``, ``_request_class``, ``_response_class``) whose
    request and response are :func:`raw_message_class` classes: ``rospy.Service`` and
    ``rospy.ServiceProxy`` then carry the serialized bytes untouched."""
    return type(f"Raw_{ident.type.replace('/', '_')}", (), {
        "_type": ident.type, "_md5sum": ident.md5sum,
        "_request_class": raw_message_class(ident.request), "_response_class": raw_message_class(ident.response)})
