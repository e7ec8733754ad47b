"""The live drive page's server (docs/live-page.md): HTTP/1.1 and WebSocket on asyncio, standard library only,
in a **server process** of its own (:func:`server_child`, a plain child interpreter of serve; it imports neither
the drive nor numba), so that its clients cost that process the CPU and the interpreter lock, not serve's.
serve's side (service.py) hands it the listening socket, a shared-memory segment with every drive cycle's
samples and each axis' state message (ring.py), and a socket pair for the requests only the drives can answer.

Routes (``NAME``: an axis name, percent-encoded):

- ``GET /`` the page; ``GET /static/FILE`` its scripts, styles and the vendored plotting library (uPlot);
- ``GET /api/axes``: the served axes and what the page may do (writes, fault injection);
- ``GET /api/axes/NAME/objects``: the object dictionary (EDS name, type, access, limits, note; the value as an
  SDO upload reads it), from serve;
- ``GET /api/axes/NAME/live``: the same messages over a WebSocket (what the page uses: a browser opens at most
  6 event streams per server, a WebSocket per tab has no such limit);
- ``GET /api/axes/NAME/events``: server-sent events: ``scope`` (every drive cycle's samples since the last
  message, float32, base64, ~60 per second) and ``state`` (CiA 402 / NMT state, faults, warnings, EMCY frames
  and SDO aborts, bus load, late cycles; 10 per second);
- ``GET /api/axes/NAME/recording.csv?from=SEQ&to=SEQ``: samples SEQ..to-1 as a trace (docs/reference/
  trace-format.md), one row per drive cycle;
- ``POST /api/axes/NAME/write`` ``{"index": 24705, "sub": 0, "value": 1000}`` (with ``--http-writable``):
  an SDO download of the slave (same checks, same abort codes), applied by serve;
- ``POST /api/axes/NAME/fault`` (with ``--http-writable`` and ``--allow-fault-injection``): the MQTT
  ``fault/set`` command format, applied by serve.

Each message is built once per tick and axis and queued to every stream of the axis. Refusals are JSON
``{"error": ...}`` with a 4xx status (and ``abort_code`` where an SDO would abort), or 501 (Transfer-Encoding),
503 (too many streams or recordings at once, serve busy) and 505 (an HTTP version other than 1.0 / 1.1); a
request the server cannot parse gets 400 and the connection is closed. Nothing is changed by a refused request.

Cross-site requests: a POST body must be ``Content-Type: application/json`` (which a browser sends to another
site only after a CORS preflight this server never answers), a POST or a WebSocket handshake whose ``Origin``
is not the ``http://`` origin its ``Host`` header names is refused (403), and a server listening on a loopback
address answers only requests whose ``Host`` names loopback (``localhost``, ``127.0.0.1``, ``[::1]``), so that a
web page whose name was re-pointed to 127.0.0.1 (DNS rebinding) is not served either. The bodies are checked
for their shape and types here, before anything is forwarded to serve.
"""

from __future__ import annotations

import asyncio
import base64
import codecs
import contextlib
import ipaddress
import itertools
import json
import os
import re
import socket
import tempfile
import threading
import time
import urllib.parse
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from virtualaxis.services import listen
from virtualaxis.services.child import ParentLink, enter_child
from virtualaxis.services.http.ring import COLUMNS, LongRing, PageBlock, RecordingError

SCOPE_HZ = 60.0  # scope messages per second and stream
STATE_EVERY = 6  # a state message every this many scope ticks (10 per second)
MAX_STREAMS = 64  # event streams open at once (all axes)
STREAM_QUEUE = 120  # messages queued per stream; a stream that falls further behind skips (and is told)
MAX_REQUEST_LINE = 2048
MAX_HEADER_BYTES = 8192
MAX_BODY_BYTES = 4096
MAX_JSON_DEPTH = 4  # nesting of a request body (the bodies are flat objects)
MAX_RECORDINGS = 4  # recording downloads at once (more: 503 with Retry-After)
RECORDING_RETRY_S = 1  # the Retry-After of such a 503 [s]
READ_TIMEOUT_S = 10.0
SEND_TIMEOUT_S = 60.0  # a response not taken by the client in this time ends its connection
REQUEST_TIMEOUT_S = 10.0  # serve's answer to a forwarded request
STATS_PERIOD_S = 1.0  # the server's counters to serve

STATIC_TYPES = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
    "uPlot.iife.min.js": "text/javascript; charset=utf-8",
    "uPlot.min.css": "text/css; charset=utf-8",
    "uPlot-LICENSE": "text/plain; charset=utf-8",
}
REASONS = {200: "OK", 400: "Bad Request", 403: "Forbidden", 404: "Not Found", 405: "Method Not Allowed",
           408: "Request Timeout", 409: "Conflict", 410: "Gone", 411: "Length Required", 413: "Content Too Large",
           414: "URI Too Long", 415: "Unsupported Media Type", 417: "Expectation Failed",
           422: "Unprocessable Content",
           431: "Request Header Fields Too Large", 500: "Internal Server Error", 501: "Not Implemented",
           503: "Service Unavailable", 505: "HTTP Version Not Supported"}


AXIS_RESOURCES = ("objects", "recording.csv", "events", "live", "write", "fault")  # (/api/axes/NAME/...)

# header fields a request may carry at most once (RFC 9112 6.3, 3.2; RFC 6455 4.2.1): a second one, even with the
# same value, is refused; the others may repeat and are joined with ", " (RFC 9110 5.3)
SINGLE_HEADERS = frozenset({"content-length", "content-type", "host", "origin", "sec-websocket-key",
                            "sec-websocket-version"})
_TOKEN = re.compile(r"[!#$%&'*+\-.^_`|~0-9A-Za-z]+")  # a header name (RFC 9110 5.1)
_DIGITS = re.compile(r"[0-9]+")  # (str.isdigit and int() would also take other scripts' digits)
_INDEX = re.compile(r"0[xX][0-9A-Fa-f]+|[0-9]+")
_HOST = re.compile(r"(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9\-._~%!$&'()*+,;=]+)(?::(?P<port>[0-9]{0,5}))?")
_WS_CLOSE_CODES = frozenset([*range(1000, 1004), *range(1007, 1015), *range(3000, 5000)])  # RFC 6455 7.4
_ABORT_INVALID_VALUE = 0x06090030
FAULT_KEYS = ("action", "kind", "duty", "period_s", "magnitude", "id")


class HttpRefusal(Exception):
    """A request refused with ``status`` and a JSON body (``error`` plus ``extra``); ``headers`` go with the
    answer (e.g. ``Retry-After``)."""

    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None, **extra: Any):
        super().__init__(message)
        self.status = status
        self.headers = dict(headers or {})
        self.extra = extra


def check_fault_injection(writable: bool, allowed: bool) -> None:
    """Fault injection through the page needs serve with ``--http-writable`` (``writable``) and
    ``--allow-fault-injection`` (``allowed``): HttpRefusal 403 naming the missing flag otherwise."""
    missing = [flag for flag, on in (("--http-writable", writable), ("--allow-fault-injection", allowed)) if not on]
    if missing:
        raise HttpRefusal(403, "fault injection through the page is off: it needs serve with --http-writable and "
                          f"--allow-fault-injection (missing: {' and '.join(missing)})", abort_code="0x08000022")


def parse_index(v: Any, key: str, high: int) -> int:
    """An object index / sub-index as a JSON integer or a string of ASCII digits, decimal (``"24705"``) or ``0x``
    and hexadecimal digits (``"0x6081"``); HttpRefusal 400 naming ``key`` for anything else (a float such as
    4.0, signs, blanks, underscores, other scripts' digits) or a number beyond 0..``high``."""
    if isinstance(v, str):
        if len(v) > 12 or not _INDEX.fullmatch(v):
            raise HttpRefusal(400, f"{key}: {v[:20]!r} is not a number (decimal digits, or 0x and hex digits as "
                              "in \"0x6081\")")
        v = int(v, 16) if v[1:2] in ("x", "X") else int(v, 10)
    if isinstance(v, bool) or not isinstance(v, int):
        got = json.dumps(v)[:20] if isinstance(v, float) else type(v).__name__
        raise HttpRefusal(400, f"{key}: must be an integer or a string like \"0x6081\" (got {got})")
    if not 0 <= v <= high:
        raise HttpRefusal(400, f"{key}: must be 0..0x{high:X} (got {v})")
    return v


def parse_host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[v6]:PORT``) of ``--http``; ValueError naming the option."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host:
        raise ValueError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"--http {text!r}: port {port!r} is not a number") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"--http {text!r}: port must be 0..65535 (0: any free port)")
    return host, p


def check_listen(host: str, port: int) -> None:
    """ValueError naming ``--http`` and the cause if the page could not listen on ``host:port`` (its
    ``socketserver`` server binds the first address ``host`` resolves to)."""
    listen.check_listen(host, port, option="--http", every_address=False)


def eds_notes(eds_path: str | Path) -> dict[int, str]:
    """The EDS's ``[Comments]`` lines ``0xIIII Name: note`` by index (units and meanings of the objects)."""
    import configparser

    cp = configparser.ConfigParser(interpolation=None, strict=False)
    cp.optionxform = str
    try:
        cp.read(eds_path, encoding="utf-8")
    except (configparser.Error, OSError, UnicodeDecodeError):
        return {}
    notes: dict[int, str] = {}
    if cp.has_section("Comments"):
        for key, line in cp.items("Comments"):
            if not key.startswith("Line") or not line.startswith("0x"):
                continue
            head, _, note = line.partition(" ")
            try:
                index = int(head, 16)
            except ValueError:
                continue
            notes[index] = note.partition(": ")[2] or note
    return notes


class PageAxis:
    """One axis in the server process: its index in serve's list, name, ring, open streams, and whether serve
    runs it with ``--allow-fault-injection``."""

    def __init__(self, index: int, name: str, ring: LongRing, force_actuator: bool, fault_injection: bool = False):
        self.index = index
        self.name = name
        self.ring = ring
        self.force_actuator = force_actuator
        self.fault_injection = fault_injection
        self.streams: set = set()

    def opened(self, q: asyncio.Queue) -> None:
        self.streams.add(q)
        self.ring.block.set_clients(len(self.streams))

    def closed(self, q: asyncio.Queue) -> None:
        self.streams.discard(q)
        self.ring.block.set_clients(len(self.streams))


def server_child(link_fd: int, listen_fd: int) -> None:
    """Entry of the page's server process (child.py): ``link_fd`` joins it to serve, ``listen_fd`` is the
    page's listening socket."""
    sock = socket.socket(fileno=listen_fd)
    entered = enter_child(link_fd)
    if entered is None:
        return
    link, (_, spec) = entered
    try:
        server = PageServer(link, sock, spec)
    except Exception as exc:  # noqa: BLE001 - reported to serve as a start-up error
        link.send(("error", f"{type(exc).__name__}: {exc}"))
        raise SystemExit(1) from None
    try:
        asyncio.run(server.main())
    finally:
        server.close()


class PageServer:
    """The page's HTTP / WebSocket server in its own process (module doc)."""

    def __init__(self, link: ParentLink, sock: socket.socket, spec: dict):
        import mmap

        self.link = link
        self.writable = bool(spec["writable"])
        self.info = spec["info"]
        # attached by path, not by SharedMemory(name): in Python < 3.13 that would register the segment with a
        # resource tracker of this process, which unlinks it when this process ends (serve owns it)
        fd = os.open(f"/dev/shm/{spec['shm'].lstrip('/')}", os.O_RDWR)
        try:
            self._map = mmap.mmap(fd, 0)
        finally:
            os.close(fd)
        buf = memoryview(self._map)
        self.axes = {a["name"]: PageAxis(i, a["name"], LongRing(PageBlock(buf, i), a["cycle_s"], spec["ring_s"]),
                                         a["force_actuator"], bool(a.get("fault_injection_allowed", False)))
                     for i, a in enumerate(spec["axes"])}
        self.counters = {"requests": 0, "refused": 0, "writes_refused": 0, "streams_opened": 0,
                         "messages_skipped": 0, "ticks": 0, "recordings": 0, "recordings_refused": 0,
                         "forwarded": 0}
        sock.setblocking(False)
        self._sock = sock
        self._loopback = _is_loopback(sock.getsockname()[0])  # (then Host must name loopback: module doc)
        self._recordings = 0  # recording downloads being built or sent
        pkg = resources.files("virtualaxis.services.http") / "static"
        self._static = {name: (pkg / name).read_bytes() for name in STATIC_TYPES}
        self._stopping = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._futures: dict[int, asyncio.Future] = {}
        self._ids = itertools.count(1)

    def close(self) -> None:
        for ax in self.axes.values():
            ax.ring.block = None
        with contextlib.suppress(Exception):  # (a view still exported: the process ends anyway)
            self._map.close()

    def stats(self) -> dict:
        out = dict(self.counters)
        out["streams_open"] = sum(len(a.streams) for a in self.axes.values())
        out["samples_lost"] = {a.name: a.ring.lost for a in self.axes.values()}
        return out

    # ------------------------------------------------------------------ serve's socket
    def send(self, msg: tuple) -> None:
        self.link.send(msg)

    def _read(self) -> None:
        """serve's messages: replies, stop. EOF: serve is gone, and so is this process at once."""
        loop = self._loop
        try:
            while True:
                msg = self.link.recv()
                if msg[0] == "reply":
                    loop.call_soon_threadsafe(self._resolve, msg[1], msg[2])
                elif msg[0] == "stop":
                    break
        except (EOFError, OSError):
            os._exit(0)  # never outlive serve
        self._stopping = True

    def _resolve(self, rid: int, reply: tuple) -> None:
        fut = self._futures.get(rid)
        if fut is not None and not fut.done():
            fut.set_result(reply)

    async def forward(self, kind: str, ax: PageAxis, *args: Any) -> Any:
        """A request only serve can answer (objects, write, fault): its result, or HttpRefusal as serve refused."""
        rid = next(self._ids)
        fut = self._loop.create_future()
        self._futures[rid] = fut
        self.counters["forwarded"] += 1
        self.send((kind, rid, ax.index, *args))
        try:
            reply = await asyncio.wait_for(fut, REQUEST_TIMEOUT_S)
        except asyncio.TimeoutError:
            raise HttpRefusal(503, f"serve did not answer in {REQUEST_TIMEOUT_S:g} s") from None
        finally:
            self._futures.pop(rid, None)
        if reply[0] == "ok":
            return reply[1]
        _, status, message, extra = reply
        raise HttpRefusal(status, message, **extra)

    # ------------------------------------------------------------------ life cycle
    async def main(self) -> None:
        self._loop = asyncio.get_running_loop()
        server = await asyncio.start_server(self._client, sock=self._sock, limit=MAX_HEADER_BYTES)
        threading.Thread(target=self._read, name="virtualaxis-http-reader", daemon=True).start()
        self.send(("ready", self._sock.getsockname()[1]))
        threading.Thread(target=_load_trace_writer, daemon=True, name="virtualaxis-http-warm").start()
        ticker = asyncio.ensure_future(self._ticker())
        next_stats = 0.0
        try:
            while not self._stopping:
                await asyncio.sleep(0.05)
                if time.monotonic() >= next_stats:
                    next_stats = time.monotonic() + STATS_PERIOD_S
                    self.send(("stats", self.stats()))
        finally:
            ticker.cancel()
            server.close()
            for ax in self.axes.values():
                for q in list(ax.streams):
                    q.put_nowait(None)
            await asyncio.sleep(0.05)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1.0)
            self.send(("stats", self.stats()))

    # ------------------------------------------------------------------ periodic job
    async def _ticker(self) -> None:
        period = 1.0 / SCOPE_HZ
        n = 0
        next_t = time.monotonic()
        while not self._stopping:
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # far behind (a stalled host): no burst of catch-up ticks
                next_t = time.monotonic()
            await asyncio.sleep(max(0.0, delay))
            n += 1
            self.counters["ticks"] = n
            try:
                self._tick(n % STATE_EVERY == 0)
            except Exception:  # noqa: BLE001 - one bad tick never stops the page; the next tick tries again
                import logging

                logging.getLogger("virtualaxis.services.http").exception("live page tick failed")

    def _tick(self, with_state: bool) -> None:
        for ax in self.axes.values():
            first, end = ax.ring.drain()
            if not ax.streams:
                continue
            if end > first:
                self._broadcast(ax, b"scope", self._scope_message(ax, first, end))
            if with_state:
                state = ax.ring.state_message()
                if state:
                    self._broadcast(ax, b"state", state)

    def _broadcast(self, ax: PageAxis, event: bytes, data: bytes) -> None:
        msg = (event, data)
        for q in ax.streams:
            if q.full():
                self.counters["messages_skipped"] += 1
                continue
            q.put_nowait(msg)

    @staticmethod
    def _scope_message(ax: PageAxis, first: int, end: int) -> bytes:
        times, rows = ax.ring.slice(first, end)
        b64 = base64.b64encode(rows.astype(np.float32).tobytes()).decode("ascii")
        return json.dumps({"seq0": first, "t0": float(times[0]), "dt": ax.ring.cycle_s, "n": end - first,
                           "cols": len(COLUMNS), "b64": b64}).encode()

    # ------------------------------------------------------------------ HTTP
    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await self._serve_one(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.CancelledError):
            pass
        except Exception:  # noqa: BLE001 - one bad connection never stops the server
            import logging

            logging.getLogger("virtualaxis.services.http").exception("live page request failed")
            with contextlib.suppress(Exception):
                self._respond_json(writer, 500, {"error": "internal error (logged by serve)"})
        finally:
            with contextlib.suppress(Exception):
                writer.close()

    async def _serve_one(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            method, raw_path, query, headers, body = await asyncio.wait_for(self._read_request(reader, writer),
                                                                            READ_TIMEOUT_S)
        except HttpRefusal as exc:
            await self._refuse(writer, exc)
            return
        except asyncio.TimeoutError:
            await self._refuse(writer, HttpRefusal(408, f"request not complete within {READ_TIMEOUT_S:g} s"))
            return
        self.counters["requests"] += 1
        route = _axis_route(raw_path)
        with contextlib.ExitStack() as held:  # (what the answer holds until it is sent: a recording's slot)
            try:
                if route is not None and route[1] == "live" and method == "GET":
                    await self._websocket(self._axis(route[0]), headers, reader, writer)
                    return
                if "upgrade" in headers:
                    raise HttpRefusal(400, f"no protocol upgrade here (asked for {headers['upgrade'][:30]!r}): the "
                                      "WebSocket of the live updates is /api/axes/NAME/live")
                if route is not None and route[1] == "events" and method == "GET":
                    await self._stream(self._axis(route[0]), writer)
                    return
                status, ctype, payload, extra_headers = await self._route(method, raw_path, route, query, headers,
                                                                          body, held)
            except HttpRefusal as exc:
                await self._refuse(writer, exc)
                return
            self._respond(writer, status, ctype, payload, extra_headers)
            await self._send(writer)

    async def _refuse(self, writer: asyncio.StreamWriter, exc: HttpRefusal) -> None:
        self.counters["refused"] += 1
        self._respond_json(writer, exc.status, {"error": str(exc), **exc.extra}, exc.headers)
        await self._send(writer)

    @staticmethod
    async def _send(writer: asyncio.StreamWriter) -> None:
        """Wait until the answer is (nearly all) with the kernel; a client that does not take it within
        SEND_TIMEOUT_S loses its connection."""
        try:
            await asyncio.wait_for(_drain(writer), SEND_TIMEOUT_S)
        except asyncio.TimeoutError:
            writer.transport.abort()

    async def _read_request(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter):
        try:
            line = await reader.readuntil(b"\n")
        except asyncio.LimitOverrunError:
            raise HttpRefusal(414, f"request line longer than {MAX_HEADER_BYTES} bytes") from None
        except asyncio.IncompleteReadError as exc:
            if not exc.partial:
                raise ConnectionError("closed before a request") from None
            raise HttpRefusal(400, "request line not terminated") from None
        if len(line) > MAX_REQUEST_LINE:
            raise HttpRefusal(414, f"request line is {len(line)} bytes (at most {MAX_REQUEST_LINE})")
        try:
            text = line.decode("ascii").rstrip("\r\n")
        except UnicodeDecodeError:
            raise HttpRefusal(400, "request line is not ASCII") from None
        parts = text.split(" ")
        if len(parts) != 3 or not parts[0] or not parts[1]:
            raise HttpRefusal(400, f"malformed request line {text[:80]!r} (expected METHOD TARGET HTTP/1.x)")
        method, target, version = parts
        if version not in ("HTTP/1.1", "HTTP/1.0"):
            raise HttpRefusal(505 if version.startswith("HTTP/") else 400,
                              f"unsupported protocol {version[:20]!r} (HTTP/1.1 or HTTP/1.0)")
        headers: dict[str, str] = {}
        total = 0
        while True:
            try:
                hline = await reader.readuntil(b"\n")
            except asyncio.LimitOverrunError:
                raise HttpRefusal(431, f"a header line is longer than {MAX_HEADER_BYTES} bytes") from None
            total += len(hline)
            if total > MAX_HEADER_BYTES:
                raise HttpRefusal(431, f"headers longer than {MAX_HEADER_BYTES} bytes")
            if hline in (b"\r\n", b"\n"):
                break
            try:
                h = hline.decode("latin-1").rstrip("\r\n")
            except UnicodeDecodeError:  # (latin-1 decodes every byte)
                raise HttpRefusal(400, "header is not text") from None
            name, sep, value = h.partition(":")
            if not sep or not _TOKEN.fullmatch(name):
                raise HttpRefusal(400, f"malformed header line {h[:60]!r}")
            key, value = name.lower(), value.strip(" \t")
            if key in headers:
                if key in SINGLE_HEADERS:
                    raise HttpRefusal(400, f"{name[:40]} header more than once (at most one is allowed)")
                headers[key] += ", " + value
            else:
                headers[key] = value
        if "transfer-encoding" in headers:
            raise HttpRefusal(501, "Transfer-Encoding is not supported (send Content-Length)")
        self._check_host(headers, version)
        body = b""
        cl = headers.get("content-length")
        if cl is not None and (not _DIGITS.fullmatch(cl) or len(cl) > 15):
            raise HttpRefusal(400, f"Content-Length {cl[:20]!r} is not a number")
        expect = headers.get("expect")
        if expect is not None and expect.lower() != "100-continue":
            raise HttpRefusal(417, f"Expect {expect[:40]!r} cannot be met (only 100-continue is understood)")
        if method == "POST":
            if cl is None:
                raise HttpRefusal(411, "POST needs a Content-Length header")
            if int(cl) > MAX_BODY_BYTES:
                raise HttpRefusal(413, f"body of {int(cl)} bytes (at most {MAX_BODY_BYTES})")
            if expect is not None and version == "HTTP/1.1" and int(cl):
                # RFC 9110 10.1.1: the client waits for this interim answer before it sends the body
                writer.write(b"HTTP/1.1 100 Continue\r\n\r\n")
            body = await reader.readexactly(int(cl))
        elif cl is not None and int(cl) != 0:
            raise HttpRefusal(400, f"{method} with a body")
        if not target.startswith("/"):
            raise HttpRefusal(400, f"request target {target[:60]!r} must be a path starting with /")
        # origin-form (RFC 9112 3.2.1): absolute-path ["?" query]; not urlsplit, which reads "//x/y" as host x
        path, _, query_text = target.partition("?")
        try:
            urllib.parse.unquote(path, errors="strict")
        except UnicodeDecodeError:
            raise HttpRefusal(400, f"path {path[:60]!r}: a percent-escape that is not UTF-8") from None
        try:
            query = urllib.parse.parse_qs(query_text, keep_blank_values=True, strict_parsing=False,
                                          max_num_fields=16)
        except ValueError as exc:
            raise HttpRefusal(400, f"query: {exc}") from None
        return method, path, query, headers, body

    def _check_host(self, headers: dict, version: str) -> None:
        """The Host header: one (checked when read), required with HTTP/1.1, a valid ``host[:port]`` (RFC 9112
        3.2: 400 otherwise); a server on a loopback address answers only a Host that names loopback (403)."""
        host = headers.get("host")
        if host is None:
            if version == "HTTP/1.1":
                raise HttpRefusal(400, "HTTP/1.1 request without a Host header")
            return
        hp = _host_port(host)
        if hp is None:
            raise HttpRefusal(400, f"Host {host[:60]!r} is not host[:port]")
        if self._loopback and not (hp[0] == "localhost" or hp[0].endswith(".localhost") or _is_loopback(hp[0])):
            raise HttpRefusal(403, f"Host {host[:60]!r}: this server listens on loopback and answers requests for "
                              "localhost, 127.0.0.1 or [::1] only")

    @staticmethod
    def _check_origin(headers: dict) -> None:
        """A request with an ``Origin`` (a browser's, from a web page) must come from the page's own origin, the
        ``http://`` origin its Host names (403 otherwise): a POST or a WebSocket of another site is refused."""
        origin = headers.get("origin")
        if origin is None:
            return
        ours = _host_port(headers.get("host", ""))
        theirs = _origin_of(origin)
        if ours is None or theirs is None or theirs != ("http", *ours):
            raise HttpRefusal(403, f"Origin {origin[:60]!r} is not this page's (http://"
                              f"{headers.get('host', '')[:60]}): requests of other sites are refused")

    async def _route(self, method: str, raw_path: str, route: tuple[str, str] | None, query: dict, headers: dict,
                     body: bytes, held: contextlib.ExitStack):
        path = urllib.parse.unquote(raw_path)  # (checked to be UTF-8 when read)
        if path in ("/", "/index.html"):
            self._only(method, "GET")
            return 200, STATIC_TYPES["index.html"], self._static["index.html"], {}
        if path.startswith("/static/"):
            self._only(method, "GET")
            name = path[len("/static/"):]
            if name not in self._static:
                raise HttpRefusal(404, f"no static file {name[:60]!r}")
            return 200, STATIC_TYPES[name], self._static[name], {"Cache-Control": "max-age=3600"}
        if path == "/api/axes":
            self._only(method, "GET")
            return _json(200, self.info)
        if path == "/api/axes/":
            raise HttpRefusal(404, "no route '/api/axes/': the list of axes is /api/axes (no trailing slash)")
        if path.startswith("/api/axes/"):
            if route is None or not route[1]:
                raise HttpRefusal(404, f"no route {path[:80]!r}: an axis's resources are /api/axes/NAME/"
                                  f"{{{','.join(AXIS_RESOURCES)}}} (the axes: /api/axes)")
            ax = self._axis(route[0])
            what = route[1]
            if what == "objects":
                self._only(method, "GET")
                return _json(200, await self.forward("objects", ax))
            if what == "recording.csv":
                self._only(method, "GET")
                held.enter_context(self._recording_slot())
                return await self._recording(ax, query)
            if what == "write":
                self._only(method, "POST")
                self._check_origin(headers)
                if not self.writable:
                    self.counters["writes_refused"] += 1
                    raise HttpRefusal(403, "the page is read-only (serve with --http-writable to write objects)")
                return _json(200, await self.forward("write", ax, _write_body(headers, body)))
            if what == "fault":
                self._only(method, "POST")
                self._check_origin(headers)
                check_fault_injection(self.writable, ax.fault_injection)
                command = _fault_body(headers, body)
                return _json(200, await self.forward("fault", ax, json.dumps(command).encode()))
            raise HttpRefusal(404, f"axis {route[0][:40]!r} has no resource {what[:40]!r} (it has "
                              f"{', '.join(AXIS_RESOURCES)})")
        if path.startswith("//"):
            raise HttpRefusal(404, f"no route {path[:80]!r}: the path starts with an empty segment (//); the page "
                              "is at /, the API under /api/axes")
        raise HttpRefusal(404, f"no route {path[:80]!r} (the page is at /, the API under /api/axes)")

    @staticmethod
    def _only(method: str, allowed: str) -> None:
        if method != allowed:
            raise HttpRefusal(405, f"method {method[:16]!r} not allowed here (only {allowed})", allow=allowed)

    def _axis(self, name: str) -> PageAxis:
        ax = self.axes.get(name)
        if ax is None:
            raise HttpRefusal(404, f"no axis {name[:40]!r} (served: {', '.join(self.axes)})")
        return ax

    # ------------------------------------------------------------------ recording
    @contextlib.contextmanager
    def _recording_slot(self):
        """One of the MAX_RECORDINGS recording downloads at once, held until its answer is sent (HttpRefusal 503
        with Retry-After beyond): each holds the samples and the CSV text in memory meanwhile."""
        if self._recordings >= MAX_RECORDINGS:
            self.counters["recordings_refused"] += 1
            raise HttpRefusal(503, f"{MAX_RECORDINGS} recordings are being downloaded already: try again in "
                              f"{RECORDING_RETRY_S} s", headers={"Retry-After": str(RECORDING_RETRY_S)})
        self._recordings += 1
        try:
            yield
        finally:
            self._recordings -= 1

    async def _recording(self, ax: PageAxis, query: dict):
        unknown = sorted(k for k in query if k not in ("from", "to"))
        if unknown:
            raise HttpRefusal(400, f"unknown parameter(s) {', '.join(unknown)[:80]} (from, to)")
        bounds = []
        for key in ("from", "to"):
            vals = query.get(key)
            if not vals:
                raise HttpRefusal(400, f"{key}: missing (sample sequence numbers, see the scope messages' seq0)")
            if len(vals) > 1 or not _DIGITS.fullmatch(vals[0]) or len(vals[0]) > 15:
                raise HttpRefusal(400, f"{key}: must be one non-negative integer (got {vals[0][:20]!r})")
            bounds.append(int(vals[0]))
        ax.ring.drain()
        try:
            times, rows = ax.ring.slice(*bounds)
        except RecordingError as exc:
            status = 410 if "no longer" in str(exc) else 409 if "so far" in str(exc) else 400
            raise HttpRefusal(status, str(exc)) from None
        force = ax.force_actuator
        cols = {"pos_cmd": 0, "pos_fb": 1, "vel_meas": 3, ("force_drive" if force else "torque_meas"): 4,
                "current_q": 5, "following_error": 2, "statusword": 6}
        data = {"t": times, **{c: rows[:, j] for c, j in cols.items()}}
        payload = await asyncio.to_thread(trace_csv, data)  # (the page goes on streaming meanwhile)
        self.counters["recordings"] += 1
        fname = f"{_safe_file_part(ax.name)}-{bounds[0]}-{bounds[1]}.csv"
        return 200, "text/csv; charset=utf-8", payload, {"Content-Disposition": f'attachment; filename="{fname}"'}

    # ------------------------------------------------------------------ event stream
    async def _stream(self, ax: PageAxis, writer: asyncio.StreamWriter) -> None:
        if sum(len(a.streams) for a in self.axes.values()) >= MAX_STREAMS:
            self.counters["refused"] += 1
            self._respond_json(writer, 503, {"error": f"{MAX_STREAMS} event streams open already (close a tab)"})
            await _drain(writer)
            return
        q: asyncio.Queue = asyncio.Queue(STREAM_QUEUE)
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n"
                     b"Connection: keep-alive\r\nX-Content-Type-Options: nosniff\r\n\r\n"
                     b"retry: 1000\n\n")
        state = ax.ring.state_message()
        if state:
            q.put_nowait((b"state", state))
        ax.opened(q)
        self.counters["streams_opened"] += 1
        try:
            while True:
                msg = await q.get()
                if msg is None:
                    return
                writer.write(b"event: " + msg[0] + b"\ndata: " + msg[1] + b"\n\n")
                await writer.drain()
        finally:
            ax.closed(q)

    async def _websocket(self, ax: PageAxis, headers: dict, reader: asyncio.StreamReader,
                         writer: asyncio.StreamWriter) -> None:
        """The live updates over a WebSocket (RFC 6455): the messages of the event stream as text frames
        ``{"event": ..., "data": ...}``. The socket only sends: a data message from the browser is answered with
        an ``error`` message (nothing changes); a frame that breaks the protocol closes the socket with code 1002,
        1007 (a text message that is not UTF-8) or 1009 (a message over 4 KiB) and the reason (:meth:`_ws_listen`).
        A handshake from another site's page (``Origin``) is refused with 403."""
        if "websocket" not in _tokens(headers.get("upgrade", "")) or "upgrade" not in _tokens(
                headers.get("connection", "")):
            raise HttpRefusal(400, "this is the WebSocket of the live updates: send Upgrade: websocket (or read the "
                              "server-sent events at /api/axes/NAME/events)")
        self._check_origin(headers)
        key = headers.get("sec-websocket-key", "")
        try:
            valid_key = len(base64.b64decode(key, validate=True)) == 16
        except ValueError:
            valid_key = False
        if not valid_key:
            raise HttpRefusal(400, "Sec-WebSocket-Key: missing or not 16 bytes in base64")
        if headers.get("sec-websocket-version") != "13":
            raise HttpRefusal(400, "Sec-WebSocket-Version: only 13")
        if sum(len(a.streams) for a in self.axes.values()) >= MAX_STREAMS:
            raise HttpRefusal(503, f"{MAX_STREAMS} live streams open already (close a tab)")
        import hashlib

        accept = base64.b64encode(hashlib.sha1((key + _WS_GUID).encode()).digest()).decode()
        writer.write(("HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                      f"Sec-WebSocket-Accept: {accept}\r\n\r\n").encode())
        q: asyncio.Queue = asyncio.Queue(STREAM_QUEUE)
        state = ax.ring.state_message()
        if state:
            q.put_nowait((b"state", state))
        ax.opened(q)
        self.counters["streams_opened"] += 1
        listener = asyncio.ensure_future(self._ws_listen(reader, q))
        try:
            while True:
                msg = await q.get()
                if msg is None:
                    return
                if isinstance(msg, tuple):
                    writer.write(_ws_frame(0x1, b'{"event": "' + msg[0] + b'", "data": ' + msg[1] + b"}"))
                else:  # a frame of the listener (pong, close)
                    writer.write(msg)
                    if msg[0] & 0x0F == 0x8:
                        await _drain(writer)
                        return
                await writer.drain()
        finally:
            listener.cancel()
            ax.closed(q)

    async def _ws_listen(self, reader: asyncio.StreamReader, q: asyncio.Queue) -> None:
        """Frames from the browser (RFC 6455 5): ping -> pong, close -> close (its code echoed), a data message
        (fragmented or not; control frames may come between its fragments) -> an error message. Closed with 1002:
        reserved bits, an unmasked frame, an unknown opcode, a fragmented or long control frame, a continuation
        without a message started, a new data frame while a fragmented message is open, a length not in its
        shortest form or with its top bit set, a close frame of 1 byte, with a code not allowed on the wire
        (7.4) or a reason that is not UTF-8; with 1007: a text message that is not UTF-8; with 1009: a message
        (all its fragments) over MAX_BODY_BYTES. A message's payload is counted and checked, not kept."""

        def close(code: int, reason: str) -> None:
            self.counters["refused"] += 1
            send_close(code.to_bytes(2, "big") + reason.encode("ascii", "replace")[:120])

        def send_close(payload: bytes) -> None:
            while q.full():  # (the close frame must get through)
                q.get_nowait()
            q.put_nowait(_ws_frame(0x8, payload))

        message_open = False  # a fragmented data message awaits its continuation frames
        message_bytes = 0  # the payload of the message so far
        text: codecs.IncrementalDecoder | None = None  # the UTF-8 check of a text message
        try:
            while True:
                head = await reader.readexactly(2)
                fin, rsv, opcode = head[0] & 0x80, head[0] & 0x70, head[0] & 0x0F
                masked, n = head[1] & 0x80, head[1] & 0x7F
                if n == 126:
                    n = int.from_bytes(await reader.readexactly(2), "big")
                    if n < 126:
                        return close(1002, "payload length not in its shortest form")
                elif n == 127:
                    n = int.from_bytes(await reader.readexactly(8), "big")
                    if n >> 63:
                        return close(1002, "64-bit payload length with its most significant bit set")
                    if n < 1 << 16:
                        return close(1002, "payload length not in its shortest form")
                if rsv:
                    return close(1002, "reserved bits set (no extension was negotiated)")
                if not masked:
                    return close(1002, "client frames must be masked")
                if opcode not in (0x0, 0x1, 0x2, 0x8, 0x9, 0xA):
                    return close(1002, f"unknown opcode 0x{opcode:X}")
                control = opcode >= 0x8
                if control and (n > 125 or not fin):
                    return close(1002, "control frame longer than 125 bytes or fragmented")
                if opcode == 0x0 and not message_open:
                    return close(1002, "continuation frame without a message started")
                if opcode in (0x1, 0x2) and message_open:
                    return close(1002, "new data frame while a fragmented message is open (its continuation "
                                 "frames must come first)")
                if not control:
                    total = (message_bytes if opcode == 0x0 else 0) + n
                    if total > MAX_BODY_BYTES:
                        return close(1009, f"message of {total} bytes or more (at most {MAX_BODY_BYTES}; this socket "
                                     "only sends)")
                mask = await reader.readexactly(4)
                payload = _unmask(await reader.readexactly(n), mask)
                if opcode == 0x8:
                    if n == 1:
                        return close(1002, "close frame of 1 byte (a close code takes 2)")
                    if n >= 2:
                        code = int.from_bytes(payload[:2], "big")
                        if code not in _WS_CLOSE_CODES:
                            return close(1002, f"close code {code} is not allowed on the wire")
                        try:
                            payload[2:].decode("utf-8")
                        except UnicodeDecodeError:
                            return close(1002, "close reason is not UTF-8")
                    return send_close(payload[:2])  # (the peer's code echoed, RFC 6455 5.5.1)
                if opcode == 0x9:
                    if not q.full():
                        q.put_nowait(_ws_frame(0xA, payload))
                    continue
                if opcode == 0xA:
                    continue
                if opcode != 0x0:  # the first frame of a message
                    message_bytes = 0
                    text = codecs.getincrementaldecoder("utf-8")() if opcode == 0x1 else None
                message_bytes += n
                if text is not None:
                    try:
                        text.decode(payload, final=bool(fin))
                    except UnicodeDecodeError:
                        return close(1007, "text message is not UTF-8")
                message_open = not fin
                if message_open:
                    continue
                self.counters["refused"] += 1
                if not q.full():
                    err = {"error": "this socket only sends the live updates; it takes no messages (writes: POST "
                           "/api/axes/NAME/write, fault injection: POST /api/axes/NAME/fault)",
                           "received_bytes": message_bytes}
                    q.put_nowait((b"error", json.dumps(err).encode()))
        except (asyncio.IncompleteReadError, ConnectionError):
            while q.full():
                q.get_nowait()
            q.put_nowait(None)

    # ------------------------------------------------------------------ responses
    def _respond(self, writer, status: int, ctype: str, payload: bytes, extra: dict | None = None) -> None:
        head = [f"HTTP/1.1 {status} {REASONS.get(status, '')}", f"Content-Type: {ctype}",
                f"Content-Length: {len(payload)}", "Connection: close", "X-Content-Type-Options: nosniff",
                "Content-Security-Policy: default-src 'self'; style-src 'self' 'unsafe-inline'"]
        head += [f"{k}: {v}" for k, v in (extra or {}).items()]
        writer.write(("\r\n".join(head) + "\r\n\r\n").encode("latin-1") + payload)

    def _respond_json(self, writer, status: int, obj: dict, headers: dict | None = None) -> None:
        extra = {"Allow": obj.pop("allow")} if "allow" in obj else {}
        self._respond(writer, status, "application/json", json.dumps(obj, default=str).encode(),
                      {**extra, **(headers or {})})



_WS_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455


def _ws_frame(opcode: int, payload: bytes) -> bytes:
    """One unmasked, unfragmented WebSocket frame (server to client)."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, n))
    elif n < 1 << 16:
        head = bytes((0x80 | opcode, 126)) + n.to_bytes(2, "big")
    else:
        head = bytes((0x80 | opcode, 127)) + n.to_bytes(8, "big")
    return head + payload


async def _drain(writer) -> None:
    with contextlib.suppress(ConnectionError):
        await writer.drain()


def _json(status: int, obj: Any):
    return status, "application/json", json.dumps(obj, default=str, allow_nan=False).encode(), {}


def _check_json_type(content_type: str | None) -> None:
    """A POST body's Content-Type must be ``application/json`` (parameters such as ``charset=utf-8`` aside);
    HttpRefusal 415 if it is another or missing (a browser sends a body of another site's page without a
    preflight only as text/plain, form data or with no Content-Type)."""
    if content_type is None:
        raise HttpRefusal(415, "Content-Type missing: send the body as Content-Type: application/json")
    ctype = content_type.split(";")[0].strip().lower()
    if ctype != "application/json":
        raise HttpRefusal(415, f"Content-Type {ctype[:40]!r}: send application/json")


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise HttpRefusal(400, f"duplicate key {key[:40]!r} (each key at most once)")
        out[key] = value
    return out


def _json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in the JSON ``text`` (brackets inside strings do not count)."""
    depth = deepest = 0
    in_string = escaped = False
    for c in text:
        if in_string:
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth -= 1
    return deepest


def _json_body(headers: dict, body: bytes) -> Any:
    """The body as JSON: Content-Type application/json (415), UTF-8, at most MAX_JSON_DEPTH levels deep, no
    NaN / Infinity, no key twice (400)."""
    _check_json_type(headers.get("content-type"))
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        raise HttpRefusal(400, "body is not UTF-8 text") from None
    if _json_depth(text) > MAX_JSON_DEPTH:
        raise HttpRefusal(400, f"body nests arrays or objects deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except RecursionError:
        raise HttpRefusal(400, "body is not JSON (nested too deeply)") from None
    except ValueError as exc:
        raise HttpRefusal(400, f"body is not JSON ({exc})") from None


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _write_body(headers: dict, body: bytes) -> dict:
    """The body of an object write checked for its shape before it goes to serve: a JSON object of ``index``
    (a JSON integer, or a string of decimal digits or 0x and hex digits), ``sub`` (likewise, default 0) and
    ``value`` (a JSON number, or a string for the string objects). 400 for a malformed body, 422 with abort
    code 0x06090030 for a value of no object's type."""
    data = _json_body(headers, body)
    if not isinstance(data, dict):
        raise HttpRefusal(400, f"body must be a JSON object (got {type(data).__name__})")
    unknown = sorted(k for k in data if k not in ("index", "sub", "value"))
    if unknown:
        raise HttpRefusal(400, f"unknown key(s) {', '.join(map(repr, unknown))[:120]} (index, sub, value)")
    if "index" not in data:
        raise HttpRefusal(400, 'index: missing (e.g. "0x6081")')
    index, sub = parse_index(data["index"], "index", 0xFFFF), parse_index(data.get("sub", 0), "sub", 0xFF)
    if "value" not in data:
        raise HttpRefusal(400, "value: missing")
    value = data["value"]
    if not (_is_number(value) or isinstance(value, str)):
        got = "null" if value is None else "a boolean" if isinstance(value, bool) else f"a {type(value).__name__}"
        raise HttpRefusal(422, f"0x{index:04X}:{sub}: value must be a number (a string for a string object; got "
                          f"{got})", abort_code=f"0x{_ABORT_INVALID_VALUE:08X}")
    return {"index": index, "sub": sub, "value": value}


def _fault_body(headers: dict, body: bytes) -> dict:
    """The body of a fault-injection command checked for its shape before it goes to serve (which checks the
    rest as for MQTT's ``fault/set``): a JSON object of the keys FAULT_KEYS; ``action`` a string, ``kind`` a
    name or an integral number, ``duty`` / ``period_s`` numbers, ``magnitude`` a number or null, ``id``
    a string or an integer (400 naming the key otherwise)."""
    data = _json_body(headers, body)
    if not isinstance(data, dict):
        raise HttpRefusal(400, f"body must be a JSON object (got {type(data).__name__})")
    unknown = sorted(k for k in data if k not in FAULT_KEYS)
    if unknown:
        raise HttpRefusal(400, f"unknown key(s) {', '.join(map(repr, unknown))[:120]} (allowed: "
                          f"{', '.join(FAULT_KEYS)})")

    def is_int(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    checks = {"action": (lambda v: isinstance(v, str), 'a string ("inject" or "clear")'),
              # (an integral number is a kind number, 4.0 too: JSON Schema's "integer", as MQTT's fault/set takes it)
              "kind": (lambda v: isinstance(v, str) or is_int(v) or v is None
                       or (isinstance(v, float) and v.is_integer()), "a fault kind name or number"),
              "duty": (_is_number, "a number"), "period_s": (_is_number, "a number"),
              "magnitude": (lambda v: _is_number(v) or v is None, "a number or null"),
              "id": (lambda v: isinstance(v, str) or is_int(v), "a string or an integer")}
    for key, value in data.items():
        ok, what = checks[key]
        if not ok(value):
            raise HttpRefusal(400, f"{key}: must be {what} (got {json.dumps(value)[:40]})")
    return data


def _tokens(value: str) -> set[str]:
    """The comma-separated tokens of a header value, lower case."""
    return {t.strip().lower() for t in value.split(",")}


def _axis_route(raw_path: str) -> tuple[str, str] | None:
    """``(NAME, WHAT)`` of a still percent-encoded path ``/api/axes/NAME/WHAT``, each decoded once (a ``/`` in
    the name comes as %2F); None for other paths."""
    if not raw_path.startswith("/api/axes/"):
        return None
    name, sep, what = raw_path[len("/api/axes/"):].rpartition("/")
    if not sep:
        return None
    return urllib.parse.unquote(name), urllib.parse.unquote(what)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _host_port(value: str, default_port: int = 80) -> tuple[str, int] | None:
    """(host in lower case, port) of ``host[:port]`` (a Host header; ``default_port`` if no port is given); None
    if malformed."""
    m = _HOST.fullmatch(value)
    if m is None:
        return None
    port = m.group("port")
    if port and int(port) > 65535:
        return None
    return m.group("host").strip("[]").lower(), int(port) if port else default_port


def _origin_of(value: str) -> tuple[str, str, int] | None:
    """(scheme, host, port) of an Origin header ``scheme://host[:port]`` (the scheme's port if none); None for
    ``null`` or anything else."""
    scheme, sep, rest = value.partition("://")
    scheme = scheme.lower()
    if not sep or scheme not in ("http", "https") or "/" in rest or "@" in rest:
        return None
    hp = _host_port(rest, 80 if scheme == "http" else 443)
    return None if hp is None else (scheme, *hp)


def _unmask(data: bytes, mask: bytes) -> bytes:
    """A client frame's payload XOR its 4-byte masking key (RFC 6455 5.3)."""
    n = len(data)
    if not n:
        return data
    key = (mask * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "little") ^ int.from_bytes(key, "little")).to_bytes(n, "little")


def trace_csv(data: dict[str, np.ndarray]) -> bytes:
    """``data`` (``t`` and the columns) as a trace CSV (docs/reference/trace-format.md)."""
    from virtualaxis.sim.trace_io import TraceWriter

    with tempfile.TemporaryDirectory(prefix="virtualaxis-page-") as tmp:
        path = Path(tmp) / "recording.csv"
        with TraceWriter(path, [c for c in data if c != "t"]) as w:
            w.write(data)
        return path.read_bytes()


def _load_trace_writer() -> None:
    """Load (and compile) the trace writer before the first recording asks for it. At the server process's own
    priority (nice 10, below the drive), not lower: a recording requested meanwhile waits for this load (the
    import lock), and a thread niced further would hold it for minutes on a busy host."""
    trace_csv({"t": np.zeros(1), "x": np.zeros(1)})


def _safe_file_part(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:40] or "axis"
