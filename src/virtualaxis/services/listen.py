"""Listen addresses of the side channels' servers (``--modbus``, ``--opcua``, ``--http``): parsing ``HOST:PORT``
and checking, before the bus opens, that a server can listen there, with errors naming the option."""

from __future__ import annotations

import socket


def parse_host_port(text: str | None, *, option: str, default: tuple[str, int],
                    error: type[ValueError] = ValueError) -> tuple[str, int]:
    """``HOST:PORT`` (or ``[v6]:PORT``, ``HOST``, ``:PORT``; the parts left out from ``default``); ``error``
    naming ``option`` for a port that is not a number in 0..65535."""
    if not text:
        return default
    host, port = text, str(default[1])
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        if rest.startswith(":"):
            port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    host = host or default[0]
    try:
        p = int(port)
    except ValueError:
        raise error(f"{option} {text!r}: port {port!r} is not a number") from None
    if not 0 <= p <= 65535:
        raise error(f"{option} {text!r}: port must be 0..65535")
    return host, p


def check_listen(host: str, port: int, *, option: str, error: type[ValueError] = ValueError,
                 every_address: bool = True) -> None:
    """Raise ``error`` naming ``option`` and the cause (host unknown, address in use or not local, ...) if a
    server could not listen on ``host:port``: on every address ``host`` resolves to (an asyncio server binds them
    all), or with ``every_address=False`` on the first (a ``socketserver`` server binds that one)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise error(f"{option} {host}:{port}: cannot resolve {host!r} ({exc.strerror})") from None
    for family, kind, proto, _, address in infos if every_address else infos[:1]:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # (as the servers do)
            try:
                s.bind(address)
            except OSError as exc:
                raise error(f"{option} {host}:{port}: cannot listen ({exc.strerror})") from None
