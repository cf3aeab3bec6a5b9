"""Is a ``tcp://host:port`` address a Dask scheduler? ``distributed.Client``'s timeout covers only
the TCP connect, and a service that accepts and stays silent would hang it; a scheduler speaks
first, so :func:`check_dask_scheduler` waits for its 8-byte handshake length with a deadline."""

from __future__ import annotations

import socket
import struct

from ..errors import UserError

#: Seconds a scheduler has to send its handshake after the connection is accepted.
HANDSHAKE_TIMEOUT_S = 10.0
#: A handshake longer than this is not Dask's (it is a small dict of versions and options).
MAX_HANDSHAKE_BYTES = 1 << 20


def _host_port(address: str) -> tuple[str, int]:
    rest = address.split("://", 1)[1]
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        raise UserError(f"--dask {address}: give a scheduler address like tcp://host:8786")
    return host.strip("[]"), int(port)


def check_dask_scheduler(address: str, *, connect_timeout: float = 20.0,
                         handshake_timeout: float | None = None) -> None:
    """Refuse a ``tcp://`` address where no Dask scheduler answers within ``handshake_timeout``
    (UserError naming it); other schemes pass."""
    if handshake_timeout is None:
        handshake_timeout = HANDSHAKE_TIMEOUT_S
    if not address.startswith("tcp://"):
        return
    host, port = _host_port(address)
    try:
        sock = socket.create_connection((host, port), timeout=connect_timeout)
    except OSError as exc:
        raise UserError(f"--dask {address}: cannot reach the Dask scheduler ({exc.strerror or exc})") from None
    try:
        sock.settimeout(handshake_timeout)
        head = b""
        while len(head) < 8:
            try:
                chunk = sock.recv(8 - len(head))
            except TimeoutError:
                raise UserError(
                    f"--dask {address}: the service there accepted the connection but sent no Dask handshake "
                    f"within {handshake_timeout:.0f} s: it is not a Dask scheduler (check the host and port; "
                    "the scheduler's default port is 8786)") from None
            except OSError as exc:
                raise UserError(f"--dask {address}: the connection failed during the Dask handshake "
                                f"({exc.strerror or exc})") from None
            if not chunk:
                raise UserError(f"--dask {address}: the service there closed the connection without a Dask "
                                "handshake: it is not a Dask scheduler")
            head += chunk
    finally:
        sock.close()
    (length,) = struct.unpack("<Q", head)
    if not 0 < length <= MAX_HANDSHAKE_BYTES:
        raise UserError(f"--dask {address}: the service there answered {head!r}, not a Dask handshake: it is "
                        "not a Dask scheduler")
