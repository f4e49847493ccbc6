"""MCAP recordings of what RCE topics carry (``rce-fleet demo --record run.mcap``, ``rce-ros --record``).

The file is MCAP (mcap.dev/spec), written with the ``mcap`` library's ``Writer``, as ROS 1 data: one
schema per message class (encoding ``ros1msg``, its full definition as a ROS 1 bag stores it, generated
from the message registry's typestore, so node packages' classes are included), one channel per topic
(message encoding ``ros1``), each message stored as it travels inside the engine (its ROS 1
serialization, never re-encoded) with the time it was received (wall clock, ns) as its log and publish
time. Chunked and zstd-compressed with a summary and indexes, as ``mcap``'s defaults write it;
``mcap-ros1-support``'s decoder, Foxglove and Lichtblick read it.

:class:`McapRecorder` has :class:`rce_client.bag.BagRecorder`'s surface (``open``, ``write``, ``close``,
``counts``, ``summary``), so a recorder takes either; :func:`recorder_for` picks by the file's suffix.
As ``rosbag record`` does, the file is written to ``FILE.active`` and renamed when it is closed.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

from rce.foxglove.protocol import ROS1, ROS1MSG, ros1_schema
from rce.messages import MessageRegistry
from rce.messages.registry import wire_name
from rce.plumbing.errors import MessageError, RequestError

from .bag import BagRecorder, Recording

PROFILE = "ros1"        # the MCAP header's profile (mcap.dev/spec/registry: ROS 1)


class McapRecorder(Recording):
    """Writes the MCAP file ``path``; ``registry`` knows the message classes (default: the process's).

    :meth:`open` creates ``path.active``, :meth:`write` adds a message, :meth:`close` finishes the file
    (summary, indexes) and renames it to ``path``. ``counts``: messages written per topic; ``late``:
    messages offered after :meth:`close`. Raises :class:`RequestError` naming the file when it cannot be
    written."""

    def __init__(self, path: str | Path, registry: MessageRegistry | None = None):
        super().__init__(path, registry)
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
        self._writer.start(profile=PROFILE, library="rce")

    def write(self, topic: str, cls: str, payload: bytes | memoryview, stamp_ns: int | None = None) -> None:
        """Add ``payload`` (a ROS 1 serialized ``cls`` message, ``pkg/Name``) on ``topic``, received at
        ``stamp_ns`` (ns since the epoch; default now). Raises :class:`MessageError` for an unknown class or
        a topic already recorded with another class."""
        if self._writer is None:
            self.late += 1
            return
        typename = self.registry.msg_type(cls)
        entry = self._channels.get(topic)
        if entry is None:
            sid = self._schemas.get(typename)
            if sid is None:
                text = ros1_schema(self.registry.store, typename).encode()
                sid = self._schemas[typename] = self._writer.register_schema(name=wire_name(typename),
                                                                             encoding=ROS1MSG, data=text)
            entry = self._channels[topic] = (typename, self._writer.register_channel(
                topic=topic, message_encoding=ROS1, schema_id=sid))
            self.counts[topic] = 0
        elif entry[0] != typename:
            raise MessageError(f"topic {topic} is recorded as {wire_name(entry[0])}, not {cls}")
        t = time.time_ns() if stamp_ns is None else stamp_ns
        self._writer.add_message(channel_id=entry[1], log_time=t, data=bytes(payload), publish_time=t,
                                 sequence=self.counts[topic])
        self.counts[topic] += 1

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


def recorder_for(path: str | Path, registry: MessageRegistry | None = None) -> McapRecorder | BagRecorder:
    """A recorder of ``path``: MCAP for ``.mcap``, a ROS 1 bag for ``.bag``. Raises :class:`RequestError`
    for another suffix."""
    suffix = Path(path).suffix.lower()
    if suffix == ".mcap":
        return McapRecorder(path, registry)
    if suffix == ".bag":
        return BagRecorder(path, registry)
    raise RequestError(f"{path}: a recording is FILE.mcap (MCAP) or FILE.bag (ROS 1 bag), not {suffix or 'no suffix'}")
