"""The Zenoh TLS files checked before a session is opened (issue 45).

Zenoh reports nothing of a TLS link that fails: with a wrong CA, an expired certificate, a key of another
certificate or a PEM file that is none, ``check-config`` said ok, ``detect-host`` printed "ready ... publishing"
and exited 0, and neither side logged a line. So the files are checked here with the TLS library Python already
has (OpenSSL, through :mod:`ssl`): the CA file must hold a certificate, this side's certificate and key must load
as a pair, and the certificate must pass the verification the other side will make of it — a handshake in memory
(no socket) against ``tls_root_ca``, the CA both sides of mutual TLS share — which refuses a certificate signed by
another CA, expired or not yet valid. Each failure is one line naming the key, the file and OpenSSL's reason.

The files are opened through :mod:`mocapd.io.input_files` (a FIFO or a device is one line, not a wait) and handed
to OpenSSL as ``/proc/self/fd/N``, the file checked.
"""

from __future__ import annotations

import os
import ssl
from collections.abc import Iterator
from contextlib import contextmanager

from mocapd.errors import ConfigError
from mocapd.io.input_files import checked_fd

MAX_PEM_BYTES = 1 << 20
"""Largest PEM file read (a certificate chain is a few KB)."""


@contextmanager
def _checked(path: str, key: str) -> Iterator[str]:
    fd = checked_fd(path, f"zenoh.{key}", max_bytes=MAX_PEM_BYTES, error=ConfigError)
    try:
        yield f"/proc/self/fd/{fd}"
    finally:
        os.close(fd)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, ssl.SSLCertVerificationError) and exc.verify_message:
        return str(exc.verify_message)
    reason = getattr(exc, "reason", None)
    return str(reason or exc).lower().replace("_", " ")


def check_tls_files(root_ca: str, cert: str, key: str) -> None:
    """Raise :class:`~mocapd.errors.ConfigError` (one line) when the TLS files would not make a link.

    Parameters
    ----------
    root_ca, cert, key : str
        ``[zenoh] tls_root_ca``, ``tls_cert``, ``tls_key`` (empty: not set; nothing to check).
    """
    if not root_ca:
        return
    client = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    client.check_hostname = False  # Zenoh checks the peer's name itself (by IP); here only the chain and dates
    with _checked(root_ca, "tls_root_ca") as ca_path:
        try:
            client.load_verify_locations(cafile=ca_path)
        except (ssl.SSLError, ValueError) as exc:
            raise ConfigError(f"zenoh.tls_root_ca = {root_ca!r}: no CA certificate read ({_reason(exc)})") from None
    if not cert or not key:
        return
    server = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    with _checked(cert, "tls_cert") as cert_path, _checked(key, "tls_key") as key_path:
        try:
            server.load_cert_chain(cert_path, key_path)
        except ssl.SSLError as exc:
            if "KEY_VALUES_MISMATCH" in str(exc):
                raise ConfigError(f"zenoh.tls_key = {key!r}: not the key of tls_cert {cert!r}") from None
            raise ConfigError(
                f"zenoh.tls_cert = {cert!r}, tls_key = {key!r}: not a PEM certificate and its key ({_reason(exc)})"
            ) from None
    try:
        _handshake(client, server)
    except ssl.SSLCertVerificationError as exc:
        raise ConfigError(
            f"zenoh.tls_cert = {cert!r}: refused by tls_root_ca {root_ca!r}, as the other side will refuse it: "
            f"{_reason(exc)}"
        ) from None
    except ssl.SSLError as exc:
        raise ConfigError(f"zenoh.tls_cert = {cert!r}: no TLS handshake with it ({_reason(exc)})") from None


def _handshake(client: ssl.SSLContext, server: ssl.SSLContext) -> None:
    """A TLS handshake between the two contexts in memory: the client verifies the server's certificate."""
    c_in, c_out, s_in, s_out = ssl.MemoryBIO(), ssl.MemoryBIO(), ssl.MemoryBIO(), ssl.MemoryBIO()
    c = client.wrap_bio(c_in, c_out, server_side=False)
    s = server.wrap_bio(s_in, s_out, server_side=True)
    done = [False, False]
    for _ in range(16):  # a TLS 1.3 handshake takes 2-3 flights each way
        for k, side in enumerate((c, s)):
            if not done[k]:
                try:
                    side.do_handshake()
                    done[k] = True
                except ssl.SSLWantReadError:
                    pass
        s_in.write(c_out.read())
        c_in.write(s_out.read())
        if all(done):
            return
    raise ssl.SSLError("the handshake did not finish")
