"""ROS 1 bag files of what RCE topics carry (``rce-topic record``, ``rce-fleet demo --bag``).

The file is a ROS bag 2.0 (wiki.ros.org/Bags/Format/2.0), written with rosbags'
``rosbags.rosbag1.Writer``: one connection per topic, named by the topic, with its class's full
message definition and MD5 sum (generated from the message registry's typestore, so the classes
of node packages are included), each message stored as it travels inside the engine (its ROS 1
serialization) with the time it was received (wall clock, ns). Debian's ``rosbag info`` and
``rosbag play`` and the rosbags reader read it.

As ``rosbag record`` does, the bag is written to ``FILE.active`` and renamed to ``FILE`` when it
is closed (an existing ``FILE`` is replaced): a bag that was never closed keeps its
``.active`` name.

:func:`record_container` records topics of a container without the admin API: through
robot-side forwarders of a client connection (every message, none sampled).
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rce.interfaces.classes import is_ros2_name
from rce.plumbing.errors import MessageError, RequestError
from rce.messages import MessageRegistry, default_registry

if TYPE_CHECKING:
    from rce_client.connection import Connection

SETUP_TIMEOUT = 30.0      # s for the recording interfaces of :func:`record_container` to come up


class Recording:
    """What every recording file shares (a bag, :class:`rce_client.mcap_recorder.McapRecorder`): ``path``,
    the ``path.active`` it is written to until it is closed, the ``registry`` that knows the message
    classes (default: the process's), ``counts`` (messages written per topic) and ``late`` (messages
    offered after it was closed, not written)."""

    def __init__(self, path: str | Path, registry: MessageRegistry | None = None):
        self.path = Path(path)
        self.active = self.path.with_name(self.path.name + ".active")
        self.registry = registry or default_registry()
        self.counts: dict[str, int] = {}
        self.late = 0
        self._writer: Any = None

    @property
    def is_open(self) -> bool:
        """Between :meth:`open` and :meth:`close`."""
        return self._writer is not None

    @property
    def total(self) -> int:
        """Messages written, all topics."""
        return sum(self.counts.values())

    def summary(self) -> str:
        """``recorded N message(s) on K topic(s) to PATH``, with the count per topic."""
        per = ", ".join(f"{t} {n}" for t, n in sorted(self.counts.items()))
        return f"recorded {self.total} message(s) on {len(self.counts)} topic(s) to {self.path}" + \
            (f" ({per})" if per else "")


class BagRecorder(Recording):
    """Writes the bag ``path``; ``registry`` knows the message classes (default: the process's).

    :meth:`open` creates ``path.active``, :meth:`write` adds a message, :meth:`close` finishes
    the file and renames it to ``path``. ``counts``: messages written per topic; ``late``:
    messages offered after :meth:`close` (not written). Raises :class:`RequestError` naming the
    file when it cannot be written."""

    def __init__(self, path: str | Path, registry: MessageRegistry | None = None):
        super().__init__(path, registry)
        self._conns: dict[str, tuple[str, Any]] = {}     # topic -> (store type, rosbags connection)

    def open(self) -> None:
        """Start the bag (``path.active``; a stale one is replaced)."""
        from rosbags.rosbag1 import Writer, WriterError
        try:
            self.active.unlink(missing_ok=True)
            writer = Writer(self.active)
            writer.open()
        except (OSError, WriterError) as e:
            raise RequestError(f"cannot write the bag {self.active}: {e}") from None
        self._writer = writer

    def write(self, topic: str, cls: str, payload: bytes | memoryview, stamp_ns: int | None = None) -> None:
        """Add ``payload`` (a ROS 1 serialized ``cls`` message, ``pkg/Name``) on ``topic``, received
        at ``stamp_ns`` (ns since the epoch; default now). Raises :class:`MessageError` for an
        unknown class, a ROS 2 class (CDR has no place in a ROS 1 bag) or a topic already recorded
        with another class."""
        if self._writer is None:
            self.late += 1
            return
        if is_ros2_name(cls):
            raise MessageError(f"topic {topic}: a ROS 1 bag holds ROS 1 messages, not {cls} (CDR); record ROS 2 "
                               f"topics into FILE.mcap")
        typename = self.registry.msg_type(cls)
        entry = self._conns.get(topic)
        if entry is None:
            conn = self._writer.add_connection(topic, typename, typestore=self.registry.store)
            entry = self._conns[topic] = (typename, conn)
            self.counts[topic] = 0
        elif entry[0] != typename:
            raise MessageError(f"topic {topic} is recorded as {entry[0]}, not {typename}")
        self._writer.write(entry[1], time.time_ns() if stamp_ns is None else stamp_ns, bytes(payload))
        self.counts[topic] += 1

    def close(self) -> Path:
        """Finish the bag and give it its name; returns the path. Idempotent."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            from rosbags.rosbag1 import WriterError
            try:
                writer.close()
                os.replace(self.active, self.path)
            except (OSError, WriterError) as e:
                raise RequestError(f"cannot finish the bag {self.path}: {e}") from None
        return self.path


async def record_container(conn: "Connection", ctag: str, topics: list[tuple[str, str]], bag: BagRecorder, *,
                           timeout: float = SETUP_TIMEOUT) -> list[str]:
    """Record ``topics`` (``(topic, class)`` pairs) of container ``ctag`` into ``bag``: for each,
    a container ``SubscriberInterface`` on the topic connected to a ``PublisherForwarder`` of the
    robot ``conn`` is connected as, whose messages (serialized bytes) go into the bag as they
    arrive. Returns the robot-side iTags once their interfaces are up. Raises
    :class:`rce.plumbing.errors.RCEError` with the cloud's reason, or :class:`rce.plumbing.errors.Unavailable`
    after ``timeout`` s."""
    rid = conn.robot_id
    adds, links, tags = [], [], []
    for i, (topic, cls) in enumerate(topics):
        c_tag, r_tag = f"{rid}_tap{i}", f"{rid}_rec{i}"
        adds += [{"endpointTag": ctag, "interfaceTag": c_tag, "interfaceType": "SubscriberInterface",
                  "className": cls, "addr": topic},
                 {"endpointTag": rid, "interfaceTag": r_tag, "interfaceType": "PublisherForwarder", "className": cls}]
        links.append({"tagA": f"{ctag}/{c_tag}", "tagB": f"{rid}/{r_tag}"})
        conn.subscriber(r_tag, cls, lambda msg, bag_topic=topic, bag_cls=cls: bag.write(bag_topic, bag_cls, msg))
        tags.append(r_tag)
    await conn.configure({"addInterfaces": adds})
    await conn.send("CX", {"connect": links})
    await conn.barrier(timeout)
    await conn.wait_interfaces_up(tags, timeout)
    return tags
