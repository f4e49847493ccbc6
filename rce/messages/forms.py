"""The JSON forms of time, duration, images and byte arrays, and which of them one client gets.

A converter (docs/design.md, section 4.3) turns JSON into ROS messages and back. rce's own clients use
one form of each kind; the original RCE's clients (rce-comm 20130902) used others. Both are
accepted on input, always; on output each client gets the form it used (:class:`JsonForms`).

==========================  ============================================  ==================
kind                        forms                                         rce's (default)
==========================  ============================================  ==================
time                        ``secs`` ``{"secs", "nsecs"}``;               ``secs``
                            ``sec`` ``{"sec", "nanosec"}``;
                            ``iso`` an ISO 8601 string (the original's)
duration                    ``secs``, ``sec`` as time;                    ``secs``
                            ``float`` seconds (the original's)
image (``sensor_msgs/       ``json`` a message object (``data`` base64);  ``json``
Image``)                    ``png``/``jpeg`` the encoded image as a
                            binary part (the original's image converter)
byte array (``uint8[]``,    ``base64`` a string; ``binary`` a binary      ``base64``
``char[]``, ``byte[]``)     part (``key*``, docs/design.md, section 3.4)
==========================  ============================================  ==================

Sources: the original's time and duration converters (``rce-core/rce/util/converter.py``:
time ``'YYYY-MM-DDTHH:MM:SS.mmmmmm'`` from ``datetime.isoformat()``, duration
``Duration.to_sec()``), its image converter (``rce-core/rce/util/converters/image.py``:
PIL modes L, RGB, RGBA <-> mono8, rgb8, rgba8, PNG out), both in the ``rapyuta-robotics/rce``
repository; ISO 8601 (RFC 3339 profile) for the time strings.

The original wrote a time as the cloud host's local time without a zone and read a string
without a zone the same way; a cloud host runs on UTC, so here a time without a zone is UTC
and output is UTC without a zone, with microseconds (six digits, always: the original's
parser needs them). Input may carry ``Z`` or an offset and up to nine fraction digits.
"""
from __future__ import annotations

import calendar
import io
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any


TIME_FORMS = ("secs", "sec", "iso")
DURATION_FORMS = ("secs", "sec", "float")
IMAGE_FORMS = ("json", "png", "jpeg")
BYTE_ARRAY_FORMS = ("base64", "binary")
#: the time form a client used -> (time form, duration form) it gets back: one family per client
TIME_FAMILIES = {"secs": ("secs", "secs"), "sec": ("sec", "sec"), "iso": ("iso", "float"), "float": ("iso", "float")}

IMAGE_MAX_PIXELS = 64 * 2**20    # pixels, the largest image a binary part may decode to (decompression bombs)
JPEG_QUALITY = 90                # libjpeg quality (1-95) of the images sent to a client in the ``jpeg`` form
_NS = 10**9
_EPOCH = datetime(1970, 1, 1)


@dataclass
class JsonForms:
    """The JSON forms one client gets (``time``, ``duration``, ``images``, ``byte_arrays``; the
    values of :data:`TIME_FORMS`... above), and how they are chosen.

    With ``learn`` (a client's session: :class:`rce_robot.namespace.RobotNamespace` keeps one),
    each kind starts at rce's form and is set once, by the first value of that kind the client
    sends (:meth:`saw`): an ISO 8601 time or a float duration gives the original's pair (ISO time,
    float duration), ``{sec, nanosec}`` that pair, ``{secs, nsecs}`` rce's; a ``sensor_msgs/Image``
    sent as a PNG or JPEG binary part gives images in that format, one sent as an object gives
    objects; a ``uint8[]`` sent as a binary part gives binary parts, one sent as base64 gives
    base64. Without ``learn`` the forms stay as given. Raises :class:`ValueError` for an
    unknown form."""

    time: str = "secs"
    duration: str = "secs"
    images: str = "json"
    byte_arrays: str = "base64"
    learn: bool = False
    decided: set[str] = field(default_factory=set)     # the kinds a client's value has set

    def __post_init__(self) -> None:
        for name, allowed in (("time", TIME_FORMS), ("duration", DURATION_FORMS), ("images", IMAGE_FORMS),
                              ("byte_arrays", BYTE_ARRAY_FORMS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"JSON form {name}={getattr(self, name)!r}: expected one of {', '.join(allowed)}")

    @property
    def key(self) -> tuple[str, str, str, str]:
        """``(time, duration, images, byte_arrays)``: what a decoder's output depends on."""
        return (self.time, self.duration, self.images, self.byte_arrays)

    def saw(self, kind: str, form: str) -> None:
        """The client sent a value of ``kind`` (``time``, ``images``, ``byte_arrays``) in ``form``;
        the first one of each kind decides (with ``learn``)."""
        if not self.learn or kind in self.decided:
            return
        self.decided.add(kind)
        if kind == "time":
            self.time, self.duration = TIME_FAMILIES[form]
        elif kind == "images":
            self.images = form
        else:
            self.byte_arrays = form


#: rce's own forms, fixed: what a converter uses when no client's forms are given
RCE_FORMS = JsonForms()


# -- time and duration ----------------------------------------------------------------------------------
_ISO = re.compile(r"(\d{4})-(\d{2})-(\d{2})[T ](\d{2}):(\d{2}):(\d{2})(?:[.,](\d{1,9}))?"
                  r"(Z|z|[+-]\d{2}(?::?\d{2})?)?")


def iso_to_time(text: str) -> tuple[int, int]:
    """``(sec, nanosec)`` since the epoch of ISO 8601 ``text`` (``YYYY-MM-DDTHH:MM:SS[.f][Z|+HH:MM]``,
    no zone = UTC). Raises :class:`ValueError` saying what is wrong."""
    m = _ISO.fullmatch(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not an ISO 8601 time like '2013-09-02T12:00:00.000000'")
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    try:
        datetime(y, mo, d, h, mi, min(s, 59))        # checks the calendar (a leap second 60 is allowed)
    except ValueError as e:
        raise ValueError(f"{text!r}: {e}") from None
    sec = calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0))
    zone = m.group(8)
    if zone and zone not in "Zz":
        sign = -1 if zone[0] == "-" else 1
        digits = zone[1:].replace(":", "")
        sec -= sign * (int(digits[:2]) * 3600 + int(digits[2:4] or 0) * 60)
    if sec < 0:
        raise ValueError(f"{text!r} is before 1970: a ROS time cannot hold it")
    return sec, int((m.group(7) or "").ljust(9, "0"))


def time_to_iso(sec: int, nanosec: int) -> str:
    """The original's form of a time: UTC ``YYYY-MM-DDTHH:MM:SS.ffffff`` (microseconds, truncated)."""
    return (_EPOCH + timedelta(seconds=int(sec), microseconds=int(nanosec) // 1000)).isoformat(timespec="microseconds")


def seconds_to_duration(value: Any) -> tuple[int, int]:
    """``(sec, nanosec)`` (nanosec in [0, 1e9)) of a duration given in seconds (a number, or a string
    of one as the original accepted). Raises :class:`ValueError` for anything else."""
    if isinstance(value, bool):
        raise ValueError(f"{value!r} is not a number of seconds")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{value!r} is not a number of seconds") from None
    if not math.isfinite(x):
        raise ValueError(f"{value!r} is not a finite number of seconds")
    return divmod(int(round(x * _NS)), _NS)


def duration_to_seconds(sec: int, nanosec: int) -> float:
    """The original's form of a duration: float seconds."""
    return int(sec) + int(nanosec) / _NS


# -- images ----------------------------------------------------------------------------------------------
#: ROS encoding -> (PIL mode of its pixels, channel order swapped to RGB(A) first, bytes per pixel)
_ROS_TO_PIL = {"mono8": ("L", False, 1), "8UC1": ("L", False, 1), "mono16": ("I;16", False, 2),
               "16UC1": ("I;16", False, 2), "rgb8": ("RGB", False, 3), "8UC3": ("RGB", False, 3),
               "bgr8": ("RGB", True, 3), "rgba8": ("RGBA", False, 4), "8UC4": ("RGBA", False, 4),
               "bgra8": ("RGBA", True, 4)}
#: PIL mode of a decoded image -> (ROS encoding, bytes per pixel)
_PIL_TO_ROS = {"L": ("mono8", 1), "I;16": ("mono16", 2), "RGB": ("rgb8", 3), "RGBA": ("rgba8", 4)}
_PIL_FORMATS = {"png": "PNG", "jpeg": "JPEG"}


def image_from_bytes(data: bytes) -> tuple[dict, str]:
    """Decode a PNG or JPEG file into the fields of a ``sensor_msgs/Image`` (``height``, ``width``,
    ``encoding``, ``is_bigendian``, ``step`` in bytes, ``data`` a uint8 array) and its format
    (``png``/``jpeg``). Palette and bilevel images become rgb8/rgba8 and mono8, as the original's
    converter did. Raises :class:`ValueError` saying why the bytes are not such an image."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError
    try:
        img = Image.open(io.BytesIO(data))
    except Exception as e:   # Pillow's decoders raise several types (unidentified, truncated, bomb)
        why = "no known image format" if isinstance(e, UnidentifiedImageError) else str(e)
        raise ValueError(f"{len(data)} bytes are not a PNG or JPEG image ({why})") from None
    fmt = {"PNG": "png", "JPEG": "jpeg"}.get(img.format or "")
    if fmt is None:
        raise ValueError(f"a {img.format} image: only PNG and JPEG are taken")
    if img.width * img.height > IMAGE_MAX_PIXELS:
        raise ValueError(f"a {img.width}x{img.height} image is larger than {IMAGE_MAX_PIXELS} pixels")
    try:
        img.load()
    except Exception as e:   # as above: a broken file raises OSError, SyntaxError, ValueError...
        raise ValueError(f"the {fmt.upper()} image does not decode: {e}") from None
    if img.mode == "P":
        img = img.convert("RGBA" if "transparency" in img.info else "RGB")
    elif img.mode in ("1", "LA", "CMYK", "YCbCr"):
        img = img.convert({"1": "L", "LA": "RGBA"}.get(img.mode, "RGB"))
    elif img.mode == "I":
        img = img.convert("I;16")
    if img.mode not in _PIL_TO_ROS:
        raise ValueError(f"a {fmt.upper()} image in mode {img.mode} has no ROS encoding here")
    encoding, bpp = _PIL_TO_ROS[img.mode]
    raw = img.tobytes("raw", "I;16") if img.mode == "I;16" else img.tobytes()
    return ({"height": img.height, "width": img.width, "encoding": encoding, "is_bigendian": 0,
             "step": img.width * bpp, "data": np.frombuffer(raw, dtype=np.uint8).copy()}, fmt)


def image_to_bytes(msg: Any, fmt: str) -> bytes:
    """Encode ``sensor_msgs/Image`` ``msg`` (an object with its fields) as a ``png`` or ``jpeg``
    file. Raises :class:`ValueError` for an encoding the format cannot hold or data that does
    not fit ``height``, ``width`` and ``step``."""
    import numpy as np
    from PIL import Image
    if msg.encoding not in _ROS_TO_PIL:
        raise ValueError(f"encoding {msg.encoding!r} has no {fmt.upper()} form "
                         f"(one of {', '.join(sorted(_ROS_TO_PIL))})")
    mode, swap, bpp = _ROS_TO_PIL[msg.encoding]
    if fmt == "jpeg" and mode not in ("L", "RGB"):
        raise ValueError(f"encoding {msg.encoding!r} has no JPEG form (JPEG holds mono8 and rgb8/bgr8)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < w * bpp or data.size < h * step:
        raise ValueError(f"{data.size} bytes of data do not hold {h} rows of step {step} for {w} {msg.encoding} "
                         f"pixels")
    rows = data[:h * step].reshape(h, step)[:, :w * bpp]
    if mode == "I;16":
        pixels = rows.copy().view(">u2" if msg.is_bigendian else "<u2").astype("<u2")
        img = Image.frombuffer("I;16", (w, h), pixels.tobytes(), "raw", "I;16", 0, 1)
    else:
        px = rows.reshape(h, w, bpp)
        if swap:
            px = px[:, :, [2, 1, 0, 3][:bpp]]
        img = Image.frombuffer(mode, (w, h), np.ascontiguousarray(px).tobytes(), "raw", mode, 0, 1)
    out = io.BytesIO()
    img.save(out, _PIL_FORMATS[fmt], **({"quality": JPEG_QUALITY} if fmt == "jpeg" else {}))
    return out.getvalue()
