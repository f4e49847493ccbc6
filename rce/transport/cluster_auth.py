"""Authenticated internal links: the cluster key, the control-link handshake and the
data-plane credentials (docs/SECURITY.md, "Internal links").

**The cluster key** is a secret shared by every rce-master, rce-robot and rce-container of one
cluster: 32 random bytes, kept as hex text in a file of mode 0600 (``--cluster-key-file``, else
``$RCE_CLUSTER_KEY_FILE``, else :func:`default_key_path`). rce-master creates it there when it
is missing, so the processes of a one-machine engine find it with no flag; task sets on other
machines are given a copy. Environments and nodes never see it.

**Control links** (task set -> master) open with a mutual challenge-response before the first
control op: each side sends a fresh 16-byte nonce and proves it holds the key with
HMAC-SHA256 (RFC 2104) over both nonces, the link's purpose and its own role (so a proof can
be neither replayed on another link nor reflected back), compared with
:func:`hmac.compare_digest`::

    initiator -> {"auth": "hello", "v": 1, "purpose": P, "nonce": Ni, "key_id": K}
    responder -> {"auth": "challenge", "nonce": Nr, "proof": HMAC(key, "responder" P Ni Nr), "key_id": K}
    initiator -> {"auth": "response", "proof": HMAC(key, "initiator" P Ni Nr)}
    responder -> {"auth": "ok"}          (or {"auth": "refused", "reason": ...}, then it closes)

``key_id`` (a 32-bit HMAC of a fixed label, which reveals nothing of the key) lets both ends
say "the keys differ" instead of a bare refusal. :class:`Handshake` is the sans-I/O state of one
side; :func:`initiate` and :class:`Gate` run it on a stream (frames of :mod:`rce.transport.framing`, read
exactly, so nothing of what follows the handshake is consumed).

**Data-plane credentials.** Each data-plane endpoint (a robot task set, an environment) has a
*data key* derived from the cluster key and its advertised address (:meth:`ClusterKey.data_key`;
an environment gets its own from its container host, never the cluster key). When the master
connects interface ``src`` to interface ``dst`` it hands the end holding ``src`` the credential
:func:`connection_token` ``= HMAC(data_key(dst's address), "src>dst")``, and the other end the
credential of the other direction. The acceptor of a data link opens it with a nonce; before the
first frame from ``src`` to ``dst`` the dialler sends a grant ``HMAC(token, nonce "src>dst")``
(:func:`grant_proof`), which the acceptor checks with its own data key. One link between two
processes thus carries any number of connections, each proved once per link.
"""
from __future__ import annotations

import asyncio
import hashlib
import hmac
import os
import secrets
import socket
import struct
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from rce.contract import handshake as steps
from rce.transport import framing
from rce.plumbing.errors import ConfigError, ProtocolError, RCEError, RequestError, Timeout
from rce.transport.link import nodelay
from rce.transport.op_table import OpTable
from rce.plumbing.log import get_logger
from rce.plumbing.process import create_private_file

log = get_logger("rce.cluster_auth")

KEY_ENV = "RCE_CLUSTER_KEY_FILE"     # environment variable naming the key file (the flag wins)
KEY_FLAG_HELP = (f"file holding the cluster key every rce-master, rce-robot and rce-container of the cluster "
                 f"shares (default ${KEY_ENV}, else $XDG_STATE_HOME/rce/cluster-key or "
                 f"~/.local/state/rce/cluster-key, which rce-master creates when missing)")
KEY_BYTES = 32                       # bytes of a new cluster key (HMAC-SHA256's block-sized strength)
MIN_KEY_BYTES = 16                   # bytes a key file must hold at least (128 bits)
NONCE_BYTES = 16                     # bytes of each handshake nonce and each data-link nonce
VERSION = 1                          # the handshake's version (hello "v")
HANDSHAKE_TIMEOUT = 5.0              # s a peer has to complete the handshake (a loaded master answers in ms)
MAX_HANDSHAKE_FRAME = 4096           # bytes, the largest handshake frame read (they are about 200)
MAX_PENDING = 256                    # handshakes one listener runs at once; more connections are closed at once
LOGGED_REFUSALS = 20                 # refusals a Gate logs per LOG_WINDOW; more are only counted (no log flood)
LOG_WINDOW = 60.0                    # s
CONTROL = "control"                  # the purpose of task set -> master links

_HEAD = struct.Struct("!IB")
_LABEL = b"rce cluster auth v1\0"


class AuthFailed(RCEError):
    """A peer did not prove it holds the cluster key (or a credential), or we could not."""

    code = "unauthenticated"


# -- the key -----------------------------------------------------------------------------------------
def default_key_path() -> Path:
    """``$XDG_STATE_HOME/rce/cluster-key``, else ``~/.local/state/rce/cluster-key``: beside the
    master's default state file, so every rce process of one user on one machine finds it."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "rce" / "cluster-key"


def key_path(flag: Path | str | None = None) -> Path:
    """The key file to use: ``flag`` (``--cluster-key-file``), else ``$RCE_CLUSTER_KEY_FILE``,
    else :func:`default_key_path`."""
    if flag:
        return Path(flag)
    env = os.environ.get(KEY_ENV)
    return Path(env) if env else default_key_path()


class ClusterKey:
    """The cluster secret (``secret``: bytes) and what is derived from it. ``path``: where it
    was read from (for messages)."""

    def __init__(self, secret: bytes, path: Path | None = None):
        if len(secret) < MIN_KEY_BYTES:
            raise ConfigError(f"cluster key{f' in {path}' if path else ''} has {len(secret)} bytes; "
                              f"at least {MIN_KEY_BYTES} are needed")
        self.secret, self.path = secret, path
        self.key_id = self.mac(b"key id")[:4].hex()

    @classmethod
    def generate(cls) -> "ClusterKey":
        """A fresh random key (:data:`KEY_BYTES`; tests, and :meth:`load_or_create`)."""
        return cls(secrets.token_bytes(KEY_BYTES))

    @classmethod
    def load(cls, path: Path | str | None = None) -> "ClusterKey":
        """Read the key file (:func:`key_path` of ``path``): hex text, at least 32 hex digits.
        Raises :class:`ConfigError` naming the file when it is missing or malformed."""
        p = key_path(path)
        try:
            text = p.read_text().strip()
        except FileNotFoundError:
            raise ConfigError(f"no cluster key at {p}: start rce-master on this machine first (it creates one "
                              f"there), or give a copy of the master's key with --cluster-key-file or "
                              f"${KEY_ENV}") from None
        except OSError as e:
            raise ConfigError(f"cannot read the cluster key {p}: {e.strerror or e}") from None
        try:
            secret = bytes.fromhex(text)
        except ValueError:
            raise ConfigError(f"cluster key {p}: expected hex text (as rce-master writes it)") from None
        if p.stat().st_mode & 0o077:
            log.warning("the cluster key file is readable by others; chmod 600 it", path=str(p))
        return cls(secret, p)

    @classmethod
    def load_or_create(cls, path: Path | str | None = None) -> "ClusterKey":
        """rce-master's way: :meth:`load`, after creating the file at :func:`default_key_path` (mode
        0600, its directory 0700) with a fresh key when it is missing there. A file named by
        ``path`` or ``$RCE_CLUSTER_KEY_FILE`` is never created: all masters of a cluster need the
        same key, so a missing one is an error. Creation is atomic (a complete file appears, or
        the one another process created first is read)."""
        p = key_path(path)
        if p == default_key_path() and not p.exists() and create_private_file(p, cls.generate().secret.hex() + "\n"):
            log.info("created a cluster key; task sets on other machines need a copy of it", path=str(p))
        return cls.load(p)

    def mac(self, *parts: bytes) -> bytes:
        """HMAC-SHA256 of the key over ``parts`` (each length-prefixed: no two part lists collide)."""
        return _mac(self.secret, *parts)

    def data_key(self, addr: str) -> bytes:
        """The data key of the data-plane endpoint advertised at ``addr`` (``host:port``)."""
        return self.mac(b"data endpoint", addr.encode())

    def connection_token(self, src: int, dst: int, dst_addr: str) -> str:
        """(master) The hex credential that lets interface ``src`` send to interface ``dst`` at
        data address ``dst_addr``: :func:`connection_token` under ``dst_addr``'s data key."""
        return connection_token(self.data_key(dst_addr), src, dst).hex()


def _mac(key: bytes, *parts: bytes) -> bytes:
    h = hmac.new(key, _LABEL, hashlib.sha256)
    for p in parts:
        h.update(struct.pack("!I", len(p)))
        h.update(p)
    return h.digest()


def connection_token(data_key: bytes, src: int, dst: int) -> bytes:
    """The credential of direction ``src -> dst`` of one connection, under the receiving
    endpoint's ``data_key``."""
    return _mac(data_key, b"connection", f"{src}>{dst}".encode())


def token_of(token: object) -> bytes:
    """The credential a ``connect`` op carries as its ``token`` (hex), as bytes. Raises
    :class:`~rce.plumbing.errors.RequestError` naming what is wrong."""
    try:
        raw = bytes.fromhex(token or "")          # type: ignore[arg-type]  (anything else: refused below)
    except (TypeError, ValueError):
        raw = b""
    if len(raw) != hashlib.sha256().digest_size:
        raise RequestError(f"connect: 'token' must be the master's credential, 64 hex digits; got "
                           f"{str(token)[:80]!r}")
    return raw


def grant_proof(token: bytes, nonce: bytes, src: int, dst: int) -> bytes:
    """What a dialler sends on a data link (whose acceptor sent ``nonce``) to be let send
    ``src -> dst`` on it."""
    return _mac(token, b"grant", nonce, f"{src}>{dst}".encode())


def grant_frame(token: bytes, nonce: bytes, src: int, dst: int) -> dict:
    """The grant control frame ``{"grant": [src, dst], "proof": hex}`` for :func:`grant_proof`."""
    return {"grant": [src, dst], "proof": grant_proof(token, nonce, src, dst).hex()}


def check_grant(data_key: bytes | None, nonce: bytes, msg: dict) -> tuple[int, int]:
    """(acceptor) The ``(src, dst)`` a grant frame ``{"grant": [src, dst], "proof": hex}`` proves,
    under this endpoint's ``data_key`` and the link's ``nonce``. Raises :class:`AuthFailed`
    (bad proof, or no data key yet) or :class:`ProtocolError` (malformed)."""
    pair, proof = msg.get("grant"), msg.get("proof")
    if not (isinstance(pair, list) and len(pair) == 2 and all(type(x) is int and x >= 0 for x in pair)
            and isinstance(proof, str)):
        raise ProtocolError(f"a grant is {{\"grant\": [src, dst], \"proof\": hex}}, got {str(msg)[:200]}")
    src, dst = pair
    if data_key is None:
        raise AuthFailed("this data-plane endpoint has no data key yet")
    want = grant_proof(connection_token(data_key, src, dst), nonce, src, dst).hex()
    if not hmac.compare_digest(want, proof):
        raise AuthFailed(f"wrong credential for connection {src}>{dst}")
    return src, dst


def peer_pid(writer: asyncio.StreamWriter) -> int | None:
    """The pid of the process at the other end of a Unix socket, as the kernel knows it
    (``SO_PEERCRED``, unix(7)); None when the stream is not a Unix socket."""
    sock = writer.get_extra_info("socket")
    if sock is None or sock.family != socket.AF_UNIX:
        return None
    pid, _uid, _gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i")))
    return pid


# -- the handshake, sans I/O --------------------------------------------------------------------------
#: The handshake's steps: each message the peer may send (``{"auth": kind, ...}``), and the step that takes it.
HANDSHAKE = OpTable("cluster handshake", sync=True, error=ProtocolError)


class Handshake:
    """One side of the control-link handshake (module doc). ``role``: ``"initiator"`` (the
    dialler) or ``"responder"``; ``purpose``: what the link is for (both sides must agree);
    ``nonce``: this side's nonce (default: random, :data:`NONCE_BYTES`).

    The initiator sends :meth:`hello` first; each side then feeds every message it receives to
    :meth:`receive`, which returns the message to send back (or None) and raises
    :class:`AuthFailed` (wrong key, a refusal) or :class:`ProtocolError` (not this handshake).
    ``done`` is True once the peer is authenticated (and, for the responder, the ``ok`` is
    the message to send)."""

    def __init__(self, key: ClusterKey, role: str, purpose: str = CONTROL, nonce: bytes | None = None):
        if role not in ("initiator", "responder"):
            raise ValueError(f"role must be initiator or responder, not {role!r}")
        self.key, self.role, self.purpose = key, role, purpose
        self.nonce = nonce or secrets.token_bytes(NONCE_BYTES)
        self.peer_nonce = b""
        self.done = False
        self._expect = "challenge" if role == "initiator" else "hello"

    def hello(self) -> dict:
        """(initiator) The first message."""
        return {"auth": "hello", "v": VERSION, "purpose": self.purpose, "nonce": self.nonce.hex(),
                "key_id": self.key.key_id}

    def _proof(self, role: str) -> str:
        ni, nr = (self.nonce, self.peer_nonce) if self.role == "initiator" else (self.peer_nonce, self.nonce)
        return self.key.mac(role.encode(), self.purpose.encode(), ni, nr).hex()

    def receive(self, msg: dict) -> dict | None:
        """Take the peer's next message; returns ours to send (None: nothing to send)."""
        kind = msg.get("auth") if isinstance(msg, dict) else None
        if kind == "refused" and self.role == "initiator":
            raise AuthFailed(f"the peer refused us: {str(msg.get('reason'))[:200]}")
        if self.done or kind != self._expect:
            raise ProtocolError(f"cluster handshake: expected {self._expect!r}, got {str(msg)[:120]}")
        return HANDSHAKE.call(self, kind, msg)

    def _take_nonce(self, msg: steps.HandshakeHello | steps.HandshakeChallenge) -> None:
        try:
            nonce = bytes.fromhex(msg.nonce or "")
        except (TypeError, ValueError):
            nonce = b""
        if len(nonce) != NONCE_BYTES:
            raise ProtocolError(f"cluster handshake: a nonce is {2 * NONCE_BYTES} hex digits")
        self.peer_nonce = nonce

    def _check_key_id(self, msg: steps.HandshakeHello | steps.HandshakeChallenge) -> None:
        if msg.key_id != self.key.key_id:
            raise AuthFailed(f"cluster keys differ (the peer's id is {str(msg.key_id)[:16]!r}, ours "
                             f"{self.key.key_id!r}): give every process the same --cluster-key-file")

    @HANDSHAKE.op("hello", args=steps.HandshakeHello)
    def _on_hello(self, msg: steps.HandshakeHello) -> dict:
        if msg.v != VERSION or msg.purpose != self.purpose:
            raise ProtocolError(f"cluster handshake: expected version {VERSION} for {self.purpose!r}, got version "
                                f"{msg.v!r} for {str(msg.purpose)[:40]!r}")
        self._take_nonce(msg)
        self._check_key_id(msg)
        self._expect = "response"
        return {"auth": "challenge", "nonce": self.nonce.hex(), "proof": self._proof("responder"),
                "key_id": self.key.key_id}

    @HANDSHAKE.op("challenge", args=steps.HandshakeChallenge)
    def _on_challenge(self, msg: steps.HandshakeChallenge) -> dict:
        self._take_nonce(msg)
        self._check_key_id(msg)
        if not hmac.compare_digest(str(msg.proof), self._proof("responder")):
            raise AuthFailed("the peer does not hold the cluster key (wrong proof)")
        self._expect = "ok"
        return {"auth": "response", "proof": self._proof("initiator")}

    @HANDSHAKE.op("response", args=steps.HandshakeResponse)
    def _on_response(self, msg: steps.HandshakeResponse) -> dict:
        if not hmac.compare_digest(str(msg.proof), self._proof("initiator")):
            raise AuthFailed("the peer does not hold the cluster key (wrong proof)")
        self.done = True
        return {"auth": "ok"}

    @HANDSHAKE.op("ok", args=steps.HandshakeOk)
    def _on_ok(self, _msg: steps.HandshakeOk) -> None:
        self.done = True
        return None


# -- the handshake on a stream -------------------------------------------------------------------------
async def _read(reader: asyncio.StreamReader) -> dict:
    n, kind = _HEAD.unpack(await reader.readexactly(_HEAD.size))
    if kind != framing.CONTROL or not 1 <= n <= MAX_HANDSHAKE_FRAME:
        raise ProtocolError(f"cluster handshake: expected a control frame of at most {MAX_HANDSHAKE_FRAME} bytes")
    msg = framing.decode_body(kind, await reader.readexactly(n - 1))
    assert isinstance(msg, dict)
    return msg


def _write(writer: asyncio.StreamWriter, msg: dict) -> None:
    writer.transport.write(framing.encode_control(msg))


async def initiate(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, key: ClusterKey,
                   purpose: str = CONTROL, timeout: float = HANDSHAKE_TIMEOUT) -> None:
    """Run the initiator's side on a fresh stream. Raises :class:`AuthFailed` (the peer refused
    us, or proved nothing), :class:`ProtocolError` (it speaks something else; e.g. an older
    master), :class:`~rce.plumbing.errors.Timeout` after ``timeout`` s, or an :class:`OSError`
    (including EOF: :class:`asyncio.IncompleteReadError`)."""
    hs = Handshake(key, "initiator", purpose)
    try:
        async with asyncio.timeout(timeout):
            _write(writer, hs.hello())
            while not hs.done:
                out = hs.receive(await _read(reader))
                if out is not None:
                    _write(writer, out)
    except TimeoutError:
        raise Timeout(f"cluster handshake: no answer within {timeout:g} s") from None
    except asyncio.IncompleteReadError:
        raise AuthFailed("the peer closed the link during the cluster handshake") from None


async def respond(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, key: ClusterKey,
                  purpose: str = CONTROL, timeout: float = HANDSHAKE_TIMEOUT) -> None:
    """Run the responder's side; a failure is told to the peer (``refused``) before it is raised
    (:class:`AuthFailed`, :class:`ProtocolError`, :class:`~rce.plumbing.errors.Timeout`, :class:`OSError`)."""
    hs = Handshake(key, "responder", purpose)
    try:
        async with asyncio.timeout(timeout):
            while not hs.done:
                _write(writer, hs.receive(await _read(reader)))
    except TimeoutError:
        raise Timeout(f"no cluster handshake within {timeout:g} s") from None
    except asyncio.IncompleteReadError:
        raise ProtocolError("closed during the cluster handshake") from None
    except (AuthFailed, ProtocolError) as e:
        _write(writer, {"auth": "refused", "reason": e.message})
        raise


class Gate:
    """A listener's door: runs :func:`respond` on each new connection, at most ``max_pending``
    at once, within ``timeout`` s. ``owner`` names the listener in logs; ``refused`` counts the
    connections turned away by reason (``wrong_key``, ``malformed``, ``timeout``, ``closed``,
    ``busy``), ``admitted`` the others; ``on_refused(reason)`` is called for each refusal
    (metrics). At most :data:`LOGGED_REFUSALS` refusals are logged per :data:`LOG_WINDOW`; the
    next logged one says how many were not."""

    def __init__(self, key: ClusterKey, owner: str, *, purpose: str = CONTROL, timeout: float = HANDSHAKE_TIMEOUT,
                 max_pending: int = MAX_PENDING, on_refused: Callable[[str], None] | None = None):
        self.key, self.owner, self.purpose = key, owner, purpose
        self.timeout, self.max_pending, self.on_refused = timeout, max_pending, on_refused
        self.pending = self.admitted = 0
        self.refused: Counter[str] = Counter()
        self._window_start, self._logged, self._unlogged = float("-inf"), 0, 0

    async def admit(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> bool:
        """True when the peer proved it holds the key; otherwise the refusal is logged and
        counted, the stream closed, and False returned."""
        peer = writer.get_extra_info("peername")
        if self.pending >= self.max_pending:
            return self._refuse(writer, peer, "busy", f"{self.pending} handshakes in progress")
        self.pending += 1
        try:
            nodelay(writer)
            await respond(reader, writer, self.key, self.purpose, self.timeout)
        except AuthFailed as e:
            return self._refuse(writer, peer, "wrong_key", e.message)
        except ProtocolError as e:
            return self._refuse(writer, peer, "malformed", e.message)
        except Timeout as e:
            return self._refuse(writer, peer, "timeout", e.message)
        except OSError as e:
            return self._refuse(writer, peer, "closed", str(e))
        finally:
            self.pending -= 1
        self.admitted += 1
        return True

    def _refuse(self, writer: asyncio.StreamWriter, peer, reason: str, detail: str) -> bool:
        self.refused[reason] += 1
        now = asyncio.get_running_loop().time()
        if now - self._window_start >= LOG_WINDOW:
            self._window_start, self._logged = now, 0
        if self._logged < LOGGED_REFUSALS:
            self._logged += 1
            log.warning("unauthenticated link refused", listener=self.owner, peer=str(peer), reason=reason,
                        detail=detail[:200], unlogged=self._unlogged)
            self._unlogged = 0
        else:
            self._unlogged += 1
        if self.on_refused is not None:
            self.on_refused(reason)
        try:
            writer.close()
        except (RuntimeError, OSError):
            pass
        return False
