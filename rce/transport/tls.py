"""TLS at the front door (docs/SECURITY.md): the one place that builds the ssl contexts of the
engine's public listeners (rce-master's HTTP, rce-robot's websocket and rosbridge ports, given
``--tls-cert FILE --tls-key FILE``) and of its clients (``rce_client``, rce-ros, rce-topic,
rce-service, the admin-API client; ``--ca-file FILE`` or ``$RCE_CA_FILE``).

::

    ctx = server_context("server.pem", "server.key")   # ssl.SSLContext for web.TCPSite / websockets.serve
    ctx = client_context("ca.pem")                     # verifies the server against ca.pem (None: system CAs)
    certs = make_dev_certificates(Path("tls"))         # a throw-away CA and a 127.0.0.1/localhost cert (tests, demo)

Certificates are X.509 in PEM (RFC 5280, RFC 7468); the protocol is TLS 1.2 or newer (RFC 8446,
RFC 5246), as Python's ``ssl.create_default_context`` sets it up.
"""
from __future__ import annotations

import argparse
import base64
import datetime
import hashlib
import ipaddress
import os
import ssl
from dataclasses import dataclass
from pathlib import Path

from rce.plumbing.errors import ConfigError

__all__ = ["CA_FILE_ENV", "DevCertificates", "add_client_arguments", "add_server_arguments", "client_context",
           "for_url", "make_dev_certificates", "server_context", "server_context_from", "spki_sha256", "tls_failure"]

CA_FILE_ENV = "RCE_CA_FILE"           # environment variable naming the CA file a client trusts (as --ca-file)
MIN_VERSION = ssl.TLSVersion.TLSv1_2  # oldest TLS version served or spoken (RFC 8996 deprecates 1.0 and 1.1)
DEV_CERT_DAYS = 30                    # days a make_dev_certificates certificate is valid (tests and demos only)
DEV_KEY_SIZE = 2048                   # bits of the RSA keys make_dev_certificates makes (NIST SP 800-57: >= 2048)


def server_context(cert_file: str | Path, key_file: str | Path) -> ssl.SSLContext:
    """The server context for ``cert_file`` (PEM certificate chain, the server's first) and
    ``key_file`` (its PEM private key, unencrypted). Raises :class:`ConfigError` naming the file
    that cannot be read or does not fit."""
    for what, path in (("--tls-cert", cert_file), ("--tls-key", key_file)):
        if not Path(path).is_file():
            raise ConfigError(f"{what} {path}: no such file")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)       # the secure defaults, without the system's CAs:
    ctx.minimum_version = MIN_VERSION                   # a server that asks no client certificate needs none
    try:
        ctx.load_cert_chain(str(cert_file), str(key_file))
    except (ssl.SSLError, OSError) as e:
        raise ConfigError(f"--tls-cert {cert_file} / --tls-key {key_file}: cannot load the certificate and key: "
                          f"{e}") from None
    return ctx


def add_server_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """Add ``--tls-cert FILE --tls-key FILE`` (both or neither) to a server's parser; ``what``: what
    it then serves over TLS (for the help)."""
    parser.add_argument("--tls-cert", type=Path, default=None, metavar="FILE",
                   help=f"PEM certificate (chain): {what}; with --tls-key")
    parser.add_argument("--tls-key", type=Path, default=None, metavar="FILE", help="PEM private key of --tls-cert")


def server_context_from(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The server context of ``args.tls_cert``/``args.tls_key`` (:func:`add_server_arguments`), None
    without them. Raises :class:`ConfigError` when only one is given or the files do not fit."""
    if (args.tls_cert is None) != (args.tls_key is None):
        raise ConfigError("give both --tls-cert and --tls-key, or neither")
    return server_context(args.tls_cert, args.tls_key) if args.tls_cert else None


def add_client_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--ca-file FILE`` to a client's parser (:func:`client_context`)."""
    parser.add_argument("--ca-file", type=Path, default=None, metavar="FILE",
                   help=f"PEM CA certificate(s) that signed the cloud's TLS certificate, for https:// and wss:// "
                        f"(default ${CA_FILE_ENV}, else the system's CAs)")


#: client contexts made so far: (CA file, its identity on disk) -> context (:func:`client_context`)
_CLIENT_CONTEXTS: dict[tuple, ssl.SSLContext] = {}


def client_context(ca_file: str | Path | None = None) -> ssl.SSLContext:
    """The client context: verifies the server's certificate and host name against the CA(s) of
    ``ca_file`` (PEM) alone, else of ``$RCE_CA_FILE`` alone, else against the system's CAs: a CA file
    pins the cloud's CA, and a certificate from any other CA, one the system trusts included, is
    refused. Raises :class:`ConfigError` naming the CA file when it cannot be read.

    A context is made once per CA file as it is on disk (inode, size, modification time: a file
    replaced or changed is read again) and shared by the callers that ask for it, as an ``SSLContext``
    may be: loading the system's CAs costs ~50 ms of CPU, which every connection paid."""
    ca = ca_file or os.environ.get(CA_FILE_ENV) or None
    key = _ca_identity(ca)
    if key in _CLIENT_CONTEXTS:
        return _CLIENT_CONTEXTS[key]
    try:
        ctx = ssl.create_default_context(cafile=str(ca) if ca else None)
    except (ssl.SSLError, OSError) as e:
        source = "--ca-file" if ca_file else f"${CA_FILE_ENV}"
        raise ConfigError(f"{source} {ca}: cannot load the CA certificate(s): {e}") from None
    ctx.minimum_version = MIN_VERSION
    if key is not None:
        _CLIENT_CONTEXTS[key] = ctx
    return ctx


def _ca_identity(ca: str | Path | None) -> tuple | None:
    """The key of CA file ``ca`` in :data:`_CLIENT_CONTEXTS`, None when it cannot be read (no context
    is kept for it). The system's CAs (``ca`` None) are the files OpenSSL reads (``$SSL_CERT_FILE``,
    ``$SSL_CERT_DIR``, else its own), as they are now."""
    if ca is None:
        paths = ssl.get_default_verify_paths()
        return ("system", paths.capath, paths.cafile and _ca_identity(paths.cafile))
    try:
        st = os.stat(ca)
    except OSError:
        return None
    return (str(ca), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def for_url(url: str, ctx: ssl.SSLContext | None) -> ssl.SSLContext | None:
    """``ctx`` for an ``https://`` or ``wss://`` ``url``, None for a plain one (websockets refuses an
    ssl context with a ``ws://`` URL)."""
    return ctx if url.lower().startswith(("https:", "wss:")) else None


def tls_failure(error: BaseException, where: str) -> str | None:
    """A clear one-line reason when ``error`` is a TLS failure talking to ``where`` (a URL), else None:
    an untrusted certificate names the fix (``--ca-file`` / ``$RCE_CA_FILE``)."""
    cause = getattr(error, "certificate_error", None) or error
    while cause is not None and not isinstance(cause, ssl.SSLError):
        cause = cause.__cause__ or cause.__context__ or getattr(cause, "os_error", None)
    if cause is None:
        return None
    if isinstance(cause, ssl.SSLCertVerificationError):
        return (f"TLS: the certificate of {where} is not trusted ({cause.verify_message or cause}); give the CA "
                f"that signed it with --ca-file FILE or ${CA_FILE_ENV}")
    return f"TLS handshake with {where} failed: {cause.reason or cause}"


def spki_sha256(cert_pem: bytes) -> str:
    """base64 of the SHA-256 of a PEM certificate's SubjectPublicKeyInfo (RFC 7469 pin form; what
    Chromium's ``--ignore-certificate-errors-spki-list`` takes). Needs the ``cryptography`` package."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    spki = x509.load_pem_x509_certificate(cert_pem).public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    return base64.b64encode(hashlib.sha256(spki).digest()).decode()


@dataclass
class DevCertificates:
    """Files made by :func:`make_dev_certificates`: ``ca`` (the CA certificate a client trusts),
    ``cert`` and ``key`` (the server's, for ``--tls-cert`` and ``--tls-key``)."""
    ca: Path
    cert: Path
    key: Path


def make_dev_certificates(directory: Path, hosts: tuple[str, ...] = ("127.0.0.1", "localhost"),
                          name: str = "rce test") -> DevCertificates:
    """Make a throw-away CA and a server certificate for ``hosts`` (IP addresses or DNS names, as
    subjectAltName, RFC 5280 4.2.1.6) in ``directory`` (keys mode 0600), valid
    :data:`DEV_CERT_DAYS` days: for tests and demos, never for a reachable deployment. Needs the
    ``cryptography`` package (a test extra)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    directory.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.timezone.utc)
    validity = (now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=DEV_CERT_DAYS))

    def key():
        return rsa.generate_private_key(public_exponent=65537, key_size=DEV_KEY_SIZE)

    def cert(subject: str, pub, issuer: str, signer, extensions: list) -> x509.Certificate:
        b = (x509.CertificateBuilder().subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
             .issuer_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, issuer)])).public_key(pub)
             .serial_number(x509.random_serial_number()).not_valid_before(validity[0])
             .not_valid_after(validity[1]))
        for ext, critical in extensions:
            b = b.add_extension(ext, critical=critical)
        return b.sign(signer, hashes.SHA256())

    ca_key, srv_key = key(), key()
    ca = cert(f"{name} CA", ca_key.public_key(), f"{name} CA", ca_key,
              [(x509.BasicConstraints(ca=True, path_length=0), True),
               (x509.KeyUsage(False, False, False, False, False, True, True, False, False), True)])
    sans = [x509.IPAddress(ipaddress.ip_address(h)) if _is_ip(h) else x509.DNSName(h) for h in hosts]
    srv = cert(hosts[0], srv_key.public_key(), f"{name} CA", ca_key,
               [(x509.BasicConstraints(ca=False, path_length=None), True),
                (x509.SubjectAlternativeName(sans), False),
                (x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), False)])
    out = DevCertificates(directory / "ca.pem", directory / "server.pem", directory / "server.key")
    out.ca.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    out.cert.write_bytes(srv.public_bytes(serialization.Encoding.PEM))
    out.key.touch(mode=0o600)
    out.key.write_bytes(srv_key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                              serialization.NoEncryption()))
    return out


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True
