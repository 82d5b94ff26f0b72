"""Where the viewer listens and who may connect to it.

The address is checked before the server starts: viser, given a port out of range or an address of another machine,
fails in its own thread and leaves the caller waiting forever.

A browser lets any web page open a WebSocket to any address, 127.0.0.1 included, and says which page asks in the
`Origin` header; the viewer refuses the handshake unless that page is its own, so that a site open in another tab
cannot connect and read the scene (cross-site WebSocket hijacking). Accepted: no Origin (not a browser); a page
served from this machine's loopback address, on any port (an SSH tunnel forwards another port); a page from the very
address and port the browser connected to, when that is an IP address (a name could be a rebinding attacker's);
--host itself; and what --viewer-origin allows. viser 1.1 has no option for it, so the check is handed to the
websockets server while viser starts it (`origin_checked`).
"""

from __future__ import annotations

import contextlib
import http
import ipaddress
import socket
import threading
from typing import Iterator, Sequence
from urllib.parse import urlsplit

from ..errors import MCSplatError

_PATCHING = threading.Lock()


def check_listen_address(host: str, port: int) -> None:
    """A one-line MCSplatError unless the viewer can listen on `host` (an address of this machine) and `port`."""
    if not 0 <= port <= 65535:
        raise MCSplatError(f"--port {port}: a port is a number from 1 to 65535 (0: any free one)")
    try:
        addresses = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as error:
        raise MCSplatError(f"--host {host}: not a known address ({getattr(error, 'strerror', None) or error}); "
                           "give 127.0.0.1 (this machine only), 0.0.0.0 (every network) or an address of this "
                           "machine") from None
    for family, kind, protocol, _, address in addresses:
        with socket.socket(family, kind, protocol) as probe:
            try:
                probe.bind((address[0], 0))  # the address only: a busy port makes viser take the next free one
            except OSError as error:
                raise MCSplatError(f"--host {host}: cannot listen there ({error.strerror}); it is not an address of "
                                   "this machine: give 127.0.0.1, 0.0.0.0 or one of its own addresses") from None


class OriginPolicy:
    """Which web pages may open the viewer's WebSocket (the module docstring says why and which)."""

    def __init__(self, host: str, allowed: Sequence[str] = ()):
        self.host = host.strip("[]").lower()
        self.allowed = {entry.rstrip("/").lower() for entry in allowed}

    def accepts(self, origin: str | None, host_header: str | None, port: int) -> bool:
        if origin is None:
            return True
        origin = origin.rstrip("/").lower()
        try:
            page = urlsplit(origin)
            name, page_port = page.hostname, page.port or {"http": 80, "https": 443}.get(page.scheme)
        except ValueError:
            return False
        if not name:
            return False
        if origin in self.allowed or name in self.allowed or _is_loopback(name):
            return True
        if name == self.host and page_port == port:
            return True
        try:
            target = urlsplit(f"//{host_header or ''}")
            same_address = target.hostname == name and (target.port or 80) == page_port
        except ValueError:
            return False
        return same_address and _is_ip(name)


@contextlib.contextmanager
def origin_checked(policy: OriginPolicy) -> Iterator[None]:
    """While viser starts its server inside this block, give websockets' serve() a handshake check that refuses a
    WebSocket from a page `policy` does not accept (403)."""
    import websockets.asyncio.server as server

    original = server.serve

    def serve(*args, process_request=None, **kwargs):
        def checked(connection, request):
            if request.headers.get("Upgrade", "").lower() == "websocket" and not policy.accepts(
                    request.headers.get("Origin"), request.headers.get("Host"), connection.local_address[1]):
                return connection.respond(http.HTTPStatus.FORBIDDEN, "the mcsplat viewer accepts connections from "
                                          "its own page only (see --viewer-origin)\n")
            return process_request(connection, request) if process_request is not None else None

        return original(*args, process_request=checked, **kwargs)

    with _PATCHING:
        server.serve = serve
        try:
            yield
        finally:
            server.serve = original


def _is_loopback(name: str) -> bool:
    return name == "localhost" or (_is_ip(name) and ipaddress.ip_address(name).is_loopback)


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True
