"""A ``--scheduler`` address checked before any work: well formed, reachable, and a Dask scheduler.

``spctool batch --scheduler ADDRESS`` hands its pictures to an existing Dask distributed cluster.  A
wrong address must not cost the user a minute and a traceback (issue #41), so before a picture is
read the address is checked in three steps, each refused with one line:

1. the form (:func:`parse_scheduler`): ``tcp://HOST:PORT``, ``HOST:PORT`` (TCP) or ``tls://HOST:PORT``
   with the TLS certificates configured (Dask's ``distributed.comm.tls.*`` settings).  An empty value,
   a word without a port, a port outside 1-65535, ``inproc://`` (an address inside one Python process,
   never reachable from a command) or another scheme is bad usage: exit 2 at once;
2. reachability (:func:`probe_scheduler`): a TCP connection within the connect timeout
   (:data:`CONNECT_TIMEOUT_S`, ``SPCTOOL_DASK_TIMEOUT``): refused or timed out is an environment
   problem, exit 3;
3. the endpoint speaks Dask: a Dask scheduler sends its handshake as soon as a connection is accepted
   (``distributed.comm.core.Listener.on_connection``: an 8-byte little-endian frame length, then a
   msgpack message holding ``pickle-protocol``).  A server that stays silent (HTTP waits for a request),
   closes the connection or sends something else within the timeout is not a Dask scheduler: exit 2.

For TLS only reachability is checked here; the handshake is left to the Dask client itself (the bytes
are encrypted), whose connection (:mod:`spctool.batch.driver`) waits at most 30 s and fails in one line.
"""

from __future__ import annotations

import os
import re
import socket
import struct
import time
from typing import NamedTuple

from spctool.errors import SpcEnvironmentError, SpcUsageError

__all__ = ["CONNECT_TIMEOUT_S", "SchedulerAddress", "check_scheduler", "parse_scheduler", "probe_scheduler"]

#: seconds to connect to a scheduler and receive its handshake (also the Dask client's timeout)
CONNECT_TIMEOUT_S = float(os.environ.get("SPCTOOL_DASK_TIMEOUT", "5"))
#: Dask's default scheduler port (``tcp://host`` without a port)
DEFAULT_PORT = 8786
#: largest handshake accepted (a Dask handshake is about a hundred bytes)
MAX_HANDSHAKE_BYTES = 64 * 1024

_HOST = re.compile(r"[A-Za-z0-9._-]+\Z|\[[0-9A-Fa-f:.]+\]\Z")


class SchedulerAddress(NamedTuple):
    scheme: str
    host: str
    port: int

    def __str__(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"{self.scheme}://{host}:{self.port}"


def _bad(address, why: str) -> SpcUsageError:
    shown = repr(address) if len(repr(address)) <= 80 else repr(address)[:77] + "..."
    return SpcUsageError(
        f"--scheduler {shown}: {why} (expected tcp://HOST:PORT of a running Dask scheduler, e.g. "
        "tcp://scheduler-host:8786)"
    )


def parse_scheduler(address) -> SchedulerAddress:
    """The parts of a scheduler address, or SpcUsageError (module docstring, step 1)."""
    if not isinstance(address, str) or not address.strip():
        raise _bad(address, "an empty address")
    text = address.strip()
    if any(c.isspace() or ord(c) < 32 for c in text):
        raise _bad(address, "spaces or control characters in the address")
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, rest = "tcp", text
    scheme = scheme.lower()
    if scheme == "inproc":
        raise _bad(address, "inproc:// exists only inside one Python process")
    if scheme not in ("tcp", "tls"):
        raise _bad(address, f"the scheme {scheme}:// is not supported (tcp:// or tls://)")
    rest = rest.rstrip("/")
    if "/" in rest or "@" in rest or "?" in rest:
        raise _bad(address, "a path, user or query in the address")
    if rest.startswith("["):  # [IPv6]:PORT
        host, _, tail = rest[1:].partition("]")
        host_ok = bool(re.fullmatch(r"[0-9A-Fa-f:.]+", host))
        if tail and not tail.startswith(":"):
            raise _bad(address, "text after the bracketed host")
        port_text = tail[1:] if tail else None
    else:
        if rest.count(":") > 1:
            raise _bad(address, "an IPv6 address must be in brackets, [ADDRESS]:PORT")
        host, colon, port_text = rest.partition(":")
        host_ok = bool(_HOST.match(host))
        port_text = port_text if colon else None
    if not host or not host_ok:
        raise _bad(address, "no valid host name")
    if port_text is None:
        if not sep:  # a bare word ('garbage'): not an address at all
            raise _bad(address, "no port")
        port = DEFAULT_PORT  # tcp://host: Dask's default port
    elif not port_text.isdigit():
        raise _bad(address, f"the port {port_text!r} is not a number" if port_text else "no port after ':'")
    else:
        port = int(port_text)
    if not 1 <= port <= 65535:
        raise _bad(address, f"the port {port} is outside 1-65535")
    if scheme == "tls":
        _check_tls_configured(address)
    return SchedulerAddress(scheme, host, port)


def _check_tls_configured(address) -> None:
    try:
        import dask

        ca = dask.config.get("distributed.comm.tls.ca-file", None)
        cert = dask.config.get("distributed.comm.tls.client.cert", None)
    except Exception:  # noqa: BLE001 - no dask: the driver says so (pip install 'spctool[dask]')
        return
    if not ca or not cert:
        raise _bad(
            address,
            "tls:// needs certificates (Dask settings distributed.comm.tls.ca-file and "
            "distributed.comm.tls.client.cert / .key)",
        )


def probe_scheduler(addr: SchedulerAddress, timeout: float | None = None) -> None:
    """Steps 2 and 3 of the module docstring for a parsed address, within ``timeout`` seconds in all
    (default :data:`CONNECT_TIMEOUT_S`)."""
    timeout = CONNECT_TIMEOUT_S if timeout is None else float(timeout)
    deadline = time.monotonic() + timeout
    try:
        sock = socket.create_connection((addr.host, addr.port), timeout=timeout)
    except socket.gaierror as exc:
        raise SpcUsageError(f"--scheduler {addr}: unknown host {addr.host} ({exc.strerror})") from None
    except TimeoutError:
        raise SpcEnvironmentError(
            str(addr), f"no Dask scheduler answered within {timeout:g} s (SPCTOOL_DASK_TIMEOUT)"
        ) from None
    except OSError as exc:
        reason = (exc.strerror or str(exc) or type(exc).__name__).lower()
        raise SpcEnvironmentError(str(addr), f"cannot reach a Dask scheduler there ({reason})") from None
    with sock:
        if addr.scheme != "tcp":
            return
        data = _receive(sock, deadline)
    problem = _handshake_problem(data)
    if problem:
        raise SpcUsageError(f"--scheduler {addr}: not a Dask scheduler ({problem})")


def _receive(sock: socket.socket, deadline: float) -> bytes:
    """What the server sends first, until its first message is complete or the deadline passes."""
    data = b""
    while len(data) < MAX_HANDSHAKE_BYTES:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        sock.settimeout(left)
        try:
            chunk = sock.recv(4096)
        except TimeoutError:
            break
        except OSError:
            break
        if not chunk:  # closed by the server
            break
        data += chunk
        if len(data) >= 8:
            (size,) = struct.unpack_from("<Q", data)
            if size > MAX_HANDSHAKE_BYTES or len(data) >= 8 + size:
                break
    return data


def _handshake_problem(data: bytes) -> str | None:
    if not data:
        return "it sent nothing or closed the connection; an HTTP or other server waits for a request"
    if len(data) < 8:
        return f"it sent {len(data)} bytes, not a Dask handshake"
    (size,) = struct.unpack_from("<Q", data)
    if not 0 < size <= MAX_HANDSHAKE_BYTES or b"pickle-protocol" not in data[8 : 8 + size]:
        head = data[:24].decode("latin-1")
        shown = "".join(c if 32 <= ord(c) < 127 else "." for c in head)
        return f"its first bytes {shown!r} are not a Dask handshake"
    return None


def check_scheduler(address, timeout: float | None = None) -> SchedulerAddress:
    """The parsed address of a reachable Dask scheduler, or one error (module docstring)."""
    addr = parse_scheduler(address)
    probe_scheduler(addr, timeout)
    return addr
