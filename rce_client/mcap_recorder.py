"""MCAP recordings of what RCE topics carry (``rce-fleet demo --record run.mcap``, ``rce-ros --record``).

The file is MCAP (mcap.dev/spec), written with the ``mcap`` library's ``Writer``, in the well-known encodings
of MCAP's registry (https://mcap.dev/spec/registry): one schema per message class, one channel per topic, each
message stored as it travels (never re-encoded) with the time it was received (wall clock, ns) as its log and
publish time.

- A ROS 1 class (``pkg/Name``): schema encoding ``ros1msg`` (its full definition as a ROS 1 bag stores it,
  generated from the message registry's typestore, so node packages' classes are included), message encoding
  ``ros1`` (its ROS 1 serialization).
- A ROS 2 class (``pkg/msg/Name``): schema ``pkg/msg/Name`` in ``ros2msg`` (its ``.msg`` text, then each type it
  uses after a line of ``=`` and ``MSG: pkg/msg/Type``: :func:`rce.foxglove.protocol.ros2_schema`), message
  encoding ``cdr`` (its CDR bytes as they came, encapsulation header included), and the channel's metadata
  ``offered_qos_profiles``: the QoS its ROS 2 end offers (the interface's ``qos``, else ROS 2's default), as
  rosbag2 writes it (YAML, its version 9 form).

The header's profile (:func:`profile_for`) is ``ros1`` when every topic recorded is ROS 1, ``ros2`` when every one
is ROS 2 (that profile's rules), and none (``""``) for a mix. Chunked and zstd-compressed with a summary and
indexes, as ``mcap``'s defaults write it; ``mcap-ros1-support``'s and ``mcap-ros2-support``'s decoders, rosbags,
Foxglove and Lichtblick read it.

:class:`McapRecorder` has :class:`rce_client.bag.BagRecorder`'s surface (``open``, ``write``, ``close``,
``counts``, ``summary``), so a recorder takes either; :func:`recorder_for` picks by the file's suffix.
As ``rosbag record`` does, the file is written to ``FILE.active`` and renamed when it is closed.
"""
from __future__ import annotations

import os
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from rce.foxglove.protocol import CDR, ROS1, ROS1MSG, ROS2MSG, ros1_schema, ros2_schema
from rce.interfaces.classes import is_ros2_name
from rce.interfaces.qos import DEFAULT, QoS
from rce.messages import MessageRegistry
from rce.messages.registry import ROS2_PREFIX, wire_name
from rce.plumbing.errors import MessageError, RequestError

from .bag import BagRecorder, Recording

PROFILE = "ros1"        # the MCAP header's profile when nothing else is said (mcap.dev/spec/registry: ROS 1)
ROS2_PROFILE = "ros2"
Topics = Iterable[tuple[str, str, QoS | None]]     # (topic, class, QoS of its ROS 2 end or None) to be recorded


def profile_for(classes: Iterable[str]) -> str:
    """The MCAP profile of a file of ``classes``: ``ros1`` (all ROS 1, or none), ``ros2`` (all ROS 2), else ``""``."""
    kinds = {is_ros2_name(c) for c in classes}
    return ROS2_PROFILE if kinds == {True} else PROFILE if kinds <= {False} else ""


def offered_qos_profiles(qos: QoS | None) -> str:
    """A ROS 2 channel's ``offered_qos_profiles`` metadata: ``qos`` (None: ROS 2's default) as rosbag2's
    ``rosbag2_storage/qos.cpp`` writes it (a YAML list of one profile, policies by name, durations
    ``{sec, nsec}``; deadline, lifespan and liveliness lease unset: RMW_DURATION_INFINITE)."""
    q = qos or DEFAULT
    infinite = "\n    sec: 9223372036\n    nsec: 854775807"
    return (f"- history: {q.history}\n  depth: {q.depth}\n  reliability: {q.reliability}\n"
            f"  durability: {q.durability}\n  deadline:{infinite}\n  lifespan:{infinite}\n"
            f"  liveliness: automatic\n  liveliness_lease_duration:{infinite}\n"
            f"  avoid_ros_namespace_conventions: false\n")


class McapRecorder(Recording):
    """Writes the MCAP file ``path``; ``registry`` knows the message classes (default: the process's); ``profile``:
    the header's (:func:`profile_for`); ``qos``: topic -> the QoS its ROS 2 end offers (``offered_qos_profiles``).

    :meth:`open` creates ``path.active``, :meth:`write` adds a message, :meth:`close` finishes the file
    (summary, indexes) and renames it to ``path``. ``counts``: messages written per topic; ``late``:
    messages offered after :meth:`close`. Raises :class:`RequestError` naming the file when it cannot be
    written."""

    def __init__(self, path: str | Path, registry: MessageRegistry | None = None, *, profile: str = PROFILE,
                 qos: dict[str, QoS | None] | None = None):
        super().__init__(path, registry)
        self.profile = profile
        self.qos = dict(qos or {})
        self._file: Any = None
        self._schemas: dict[str, int] = {}                   # store type -> schema id
        self._channels: dict[str, tuple[str, int]] = {}      # topic -> (store type, channel id)

    def open(self) -> None:
        """Start the file (``path.active``; a stale one is replaced)."""
        from mcap.writer import Writer
        try:
            self.active.unlink(missing_ok=True)
            self._file = open(self.active, "wb")
        except OSError as e:
            raise RequestError(f"cannot write the MCAP file {self.active}: {e.strerror}") from None
        self._writer = Writer(self._file)
        self._writer.start(profile=self.profile, library="rce")

    def write(self, topic: str, cls: str, payload: bytes | memoryview, stamp_ns: int | None = None) -> None:
        """Add ``payload`` (a ``cls`` message as it travels: ROS 1 serialized for ``pkg/Name``, CDR for
        ``pkg/msg/Name``) on ``topic``, received at ``stamp_ns`` (ns since the epoch; default now). Raises
        :class:`MessageError` for an unknown class or a topic already recorded with another class."""
        if self._writer is None:
            self.late += 1
            return
        typename = self.registry.msg_type(cls)
        entry = self._channels.get(topic)
        if entry is None:
            entry = self._channels[topic] = (typename, self._channel(topic, typename))
            self.counts[topic] = 0
        elif entry[0] != typename:
            raise MessageError(f"topic {topic} is recorded as {wire_name(entry[0])}, not {cls}")
        t = time.time_ns() if stamp_ns is None else stamp_ns
        self._writer.add_message(channel_id=entry[1], log_time=t, data=bytes(payload), publish_time=t,
                                 sequence=self.counts[topic])
        self.counts[topic] += 1

    def _channel(self, topic: str, typename: str) -> int:
        """Register ``topic``'s channel (and its class's schema, once) for registry type ``typename``."""
        ros2 = typename.startswith(ROS2_PREFIX)
        sid = self._schemas.get(typename)
        if sid is None:
            if ros2:
                name = typename[len(ROS2_PREFIX):]
                text, encoding = ros2_schema(self.registry.ros2, name), ROS2MSG
            else:
                name, text, encoding = wire_name(typename), ros1_schema(self.registry.store, typename), ROS1MSG
            sid = self._schemas[typename] = self._writer.register_schema(name=name, encoding=encoding,
                                                                         data=text.encode())
        if ros2:
            return self._writer.register_channel(topic=topic, message_encoding=CDR, schema_id=sid,
                                                 metadata={"offered_qos_profiles": offered_qos_profiles(
                                                     self.qos.get(topic))})
        return self._writer.register_channel(topic=topic, message_encoding=ROS1, schema_id=sid)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add an MCAP metadata record ``name`` (string keys and values), e.g. what a player needs besides
        the messages. Ignored after :meth:`close`."""
        if self._writer is not None:
            self._writer.add_metadata(name=name, data=data)

    def close(self) -> Path:
        """Finish the file and give it its name; returns the path. Idempotent."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.finish()
                self._file.close()
                os.replace(self.active, self.path)
            except OSError as e:
                raise RequestError(f"cannot finish the MCAP file {self.path}: {e.strerror}") from None
        return self.path


def recorder_for(path: str | Path, registry: MessageRegistry | None = None,
                 topics: Topics = ()) -> McapRecorder | BagRecorder:
    """A recorder of ``path``: MCAP for ``.mcap`` (its profile and QoS from ``topics``, the topics it will
    record: :func:`profile_for`), a ROS 1 bag for ``.bag``. Raises :class:`RequestError` for another suffix."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mcap":
        topics = list(topics)
        return McapRecorder(path, registry, profile=profile_for(cls for _, cls, _ in topics),
                            qos={topic: qos for topic, _, qos in topics})
    if suffix == ".bag":
        return BagRecorder(path, registry)
    raise RequestError(f"{path}: a recording is FILE.mcap (MCAP) or FILE.bag (ROS 1 bag), not {suffix or 'no suffix'}")
