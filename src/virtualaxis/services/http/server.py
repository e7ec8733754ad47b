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
- ``POST /api/axes/NAME/fault`` (with ``--allow-fault-injection``): the MQTT ``fault/set`` command format,
  applied by serve.

Each message is built once per tick and axis and queued to every stream of the axis. Refusals are JSON
``{"error": ...}`` with a 4xx status (and ``abort_code`` where an SDO would abort); a request the server cannot
parse gets 400 and the connection is closed. Nothing is changed by a refused request.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import os
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
READ_TIMEOUT_S = 10.0
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
           414: "URI Too Long", 415: "Unsupported Media Type", 422: "Unprocessable Content",
           431: "Request Header Fields Too Large", 500: "Internal Server Error", 501: "Not Implemented",
           503: "Service Unavailable", 505: "HTTP Version Not Supported"}


class HttpRefusal(Exception):
    """A request refused with ``status`` and a JSON body (``error`` plus ``extra``)."""

    def __init__(self, status: int, message: str, **extra: Any):
        super().__init__(message)
        self.status = status
        self.extra = extra


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
    """One axis in the server process: its index in serve's list, name, ring and open streams."""

    def __init__(self, index: int, name: str, ring: LongRing, force_actuator: bool):
        self.index = index
        self.name = name
        self.ring = ring
        self.force_actuator = force_actuator
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
                                         a["force_actuator"])
                     for i, a in enumerate(spec["axes"])}
        self.counters = {"requests": 0, "refused": 0, "writes_refused": 0, "streams_opened": 0,
                         "messages_skipped": 0, "ticks": 0, "recordings": 0, "forwarded": 0}
        sock.setblocking(False)
        self._sock = sock
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
            method, path, query, headers, body = await asyncio.wait_for(self._read_request(reader), READ_TIMEOUT_S)
        except HttpRefusal as exc:
            self.counters["refused"] += 1
            self._respond_json(writer, exc.status, {"error": str(exc), **exc.extra})
            await _drain(writer)
            return
        except asyncio.TimeoutError:
            self.counters["refused"] += 1
            self._respond_json(writer, 408, {"error": f"request not complete within {READ_TIMEOUT_S:g} s"})
            await _drain(writer)
            return
        self.counters["requests"] += 1
        try:
            if path.startswith("/api/axes/") and path.endswith("/live") and method == "GET":
                ax = self._axis(path[len("/api/axes/"):-len("/live")])
                await self._websocket(ax, headers, reader, writer)
                return
            if "upgrade" in headers:
                raise HttpRefusal(400, f"no protocol upgrade here (asked for {headers['upgrade'][:30]!r}): the "
                                  "WebSocket of the live updates is /api/axes/NAME/live")
            if path.startswith("/api/axes/") and path.endswith("/events") and method == "GET":
                ax = self._axis(path[len("/api/axes/"):-len("/events")])
                await self._stream(ax, writer)
                return
            status, ctype, payload, extra_headers = await self._route(method, path, query, headers, body)
        except HttpRefusal as exc:
            self.counters["refused"] += 1
            self._respond_json(writer, exc.status, {"error": str(exc), **exc.extra})
            await _drain(writer)
            return
        self._respond(writer, status, ctype, payload, extra_headers)
        await _drain(writer)

    async def _read_request(self, reader: asyncio.StreamReader):
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
            if not sep or not name or name != name.strip() or any(c in name for c in " \t"):
                raise HttpRefusal(400, f"malformed header line {h[:60]!r}")
            headers[name.lower()] = value.strip()
        if "transfer-encoding" in headers:
            raise HttpRefusal(501, "Transfer-Encoding is not supported (send Content-Length)")
        body = b""
        if method == "POST":
            cl = headers.get("content-length")
            if cl is None:
                raise HttpRefusal(411, "POST needs a Content-Length header")
            if not cl.isdigit():
                raise HttpRefusal(400, f"Content-Length {cl[:20]!r} is not a number")
            if int(cl) > MAX_BODY_BYTES:
                raise HttpRefusal(413, f"body of {int(cl)} bytes (at most {MAX_BODY_BYTES})")
            body = await reader.readexactly(int(cl))
        elif headers.get("content-length", "0") not in ("", "0"):
            raise HttpRefusal(400, f"{method} with a body")
        split = urllib.parse.urlsplit(target)
        if not target.startswith("/"):
            raise HttpRefusal(400, f"request target {target[:60]!r} must be a path starting with /")
        path = urllib.parse.unquote(split.path, errors="strict") if "%" in split.path else split.path
        try:
            query = urllib.parse.parse_qs(split.query, keep_blank_values=True, strict_parsing=False,
                                          max_num_fields=16)
        except ValueError as exc:
            raise HttpRefusal(400, f"query: {exc}") from None
        return method, path, query, headers, body

    async def _route(self, method: str, path: str, query: dict, headers: dict, body: bytes):
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
        if path.startswith("/api/axes/"):
            rest = path[len("/api/axes/"):]
            name, sep, what = rest.rpartition("/")
            if not sep:
                raise HttpRefusal(404, f"no route {path[:80]!r} (see /api/axes)")
            ax = self._axis(name)
            if what == "objects":
                self._only(method, "GET")
                return _json(200, await self.forward("objects", ax))
            if what == "recording.csv":
                self._only(method, "GET")
                return await self._recording(ax, query)
            if what == "write":
                self._only(method, "POST")
                if not self.writable:
                    self.counters["writes_refused"] += 1
                    raise HttpRefusal(403, "the page is read-only (serve with --http-writable to write objects)")
                return _json(200, await self.forward("write", ax, _json_body(headers, body)))
            if what == "fault":
                self._only(method, "POST")
                return _json(200, await self.forward("fault", ax, body, headers.get("content-type", "")))
        raise HttpRefusal(404, f"no route {path[:80]!r} (the page is at /, the API under /api/axes)")

    @staticmethod
    def _only(method: str, allowed: str) -> None:
        if method != allowed:
            raise HttpRefusal(405, f"method {method[:16]!r} not allowed here (only {allowed})", allow=allowed)

    def _axis(self, quoted_name: str) -> PageAxis:
        name = urllib.parse.unquote(quoted_name)
        ax = self.axes.get(name)
        if ax is None:
            raise HttpRefusal(404, f"no axis {name[:40]!r} (served: {', '.join(self.axes)})")
        return ax

    # ------------------------------------------------------------------ recording
    async def _recording(self, ax: PageAxis, query: dict):
        unknown = sorted(k for k in query if k not in ("from", "to"))
        if unknown:
            raise HttpRefusal(400, f"unknown parameter(s) {', '.join(unknown)[:80]} (from, to)")
        bounds = []
        for key in ("from", "to"):
            vals = query.get(key)
            if not vals:
                raise HttpRefusal(400, f"{key}: missing (sample sequence numbers, see the scope messages' seq0)")
            if len(vals) > 1 or not vals[0].isdigit() or len(vals[0]) > 15:
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
        an ``error`` message (nothing changes); a frame that breaks the protocol (unmasked, reserved bits, unknown
        opcode, over 4 KiB) closes the socket with code 1002 / 1009 and the reason."""
        if headers.get("upgrade", "").lower() != "websocket" or "upgrade" not in headers.get("connection", "").lower():
            raise HttpRefusal(400, "this is the WebSocket of the live updates: send Upgrade: websocket (or read the "
                              "server-sent events at /api/axes/NAME/events)")
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
        """Frames from the browser: ping -> pong, close -> close, a data message -> an error message."""

        def close(code: int, reason: str) -> None:
            self.counters["refused"] += 1 if code != 1000 else 0
            while q.full():  # (the close frame must get through)
                q.get_nowait()
            q.put_nowait(_ws_frame(0x8, code.to_bytes(2, "big") + reason.encode()[:120]))

        try:
            while True:
                head = await reader.readexactly(2)
                fin, rsv, opcode = head[0] & 0x80, head[0] & 0x70, head[0] & 0x0F
                masked, n = head[1] & 0x80, head[1] & 0x7F
                if n == 126:
                    n = int.from_bytes(await reader.readexactly(2), "big")
                elif n == 127:
                    n = int.from_bytes(await reader.readexactly(8), "big")
                if rsv:
                    return close(1002, "reserved bits set (no extension was negotiated)")
                if not masked:
                    return close(1002, "client frames must be masked")
                if opcode not in (0x0, 0x1, 0x2, 0x8, 0x9, 0xA):
                    return close(1002, f"unknown opcode 0x{opcode:X}")
                if opcode >= 0x8 and (n > 125 or not fin):
                    return close(1002, "control frame longer than 125 bytes or fragmented")
                if n > MAX_BODY_BYTES:
                    return close(1009, f"message of {n} bytes (at most {MAX_BODY_BYTES}; this socket only sends)")
                mask = await reader.readexactly(4)
                payload = bytes(b ^ mask[i % 4] for i, b in enumerate(await reader.readexactly(n)))
                if opcode == 0x8:
                    return close(1000, "")
                if opcode == 0x9:
                    if not q.full():
                        q.put_nowait(_ws_frame(0xA, payload))
                    continue
                if opcode == 0xA:
                    continue
                self.counters["refused"] += 1
                if not q.full():
                    err = {"error": "this socket only sends the live updates; it takes no messages (writes: POST "
                           "/api/axes/NAME/write, fault injection: POST /api/axes/NAME/fault)",
                           "received_bytes": n}
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

    def _respond_json(self, writer, status: int, obj: dict) -> None:
        extra = {"Allow": obj.pop("allow")} if "allow" in obj else {}
        self._respond(writer, status, "application/json", json.dumps(obj, default=str).encode(), extra)



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


def _check_json_type(headers: dict) -> None:
    ctype = headers.get("content-type", "application/json").split(";")[0].strip().lower()
    if ctype not in ("application/json", ""):
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


def _json_body(headers: dict, body: bytes) -> Any:
    _check_json_type(headers)
    try:
        return json.loads(body.decode("utf-8"), parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except UnicodeDecodeError:
        raise HttpRefusal(400, "body is not UTF-8 text") from None
    except RecursionError:
        raise HttpRefusal(400, "body is not JSON (nested too deeply)") from None
    except ValueError as exc:
        raise HttpRefusal(400, f"body is not JSON ({exc})") from None


def trace_csv(data: dict[str, np.ndarray]) -> bytes:
    """``data`` (``t`` and the columns) as a trace CSV (docs/reference/trace-format.md)."""
    from virtualaxis.sim.trace_io import TraceWriter

    with tempfile.TemporaryDirectory(prefix="virtualaxis-page-") as tmp:
        path = Path(tmp) / "recording.csv"
        with TraceWriter(path, [c for c in data if c != "t"]) as w:
            w.write(data)
        return path.read_bytes()


def _load_trace_writer() -> None:
    """Load (and compile) the trace writer before the first recording asks for it, at nice 19 (this thread only:
    the CPU it takes at start goes to the drive first)."""
    with contextlib.suppress(OSError, AttributeError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    trace_csv({"t": np.zeros(1), "x": np.zeros(1)})


def _safe_file_part(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:40] or "axis"
