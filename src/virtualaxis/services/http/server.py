"""The live drive page of ``virtualaxis serve --http HOST:PORT`` (docs/live-page.md).

A small HTTP/1.1 server on asyncio in a thread of its own (like the Modbus and MQTT side channels), standard
library only. Routes (``NAME``: an axis name, percent-encoded):

- ``GET /`` the page; ``GET /static/FILE`` its scripts, styles and the vendored plotting library (uPlot);
- ``GET /api/axes``: the served axes and what the page may do (writes, fault injection);
- ``GET /api/axes/NAME/objects``: the object dictionary (EDS name, type, access, limits, note; the value as an
  SDO upload reads it);
- ``GET /api/axes/NAME/live``: the same messages over a WebSocket (what the page uses: a browser opens at most
  6 event streams per server, a WebSocket per tab has no such limit);
- ``GET /api/axes/NAME/events``: server-sent events: ``scope`` (every drive cycle's samples since the last
  message, float32, base64, ~60 per second) and ``state`` (CiA 402 / NMT state, faults, warnings, EMCY frames
  and SDO aborts, bus load, late cycles; 10 per second);
- ``GET /api/axes/NAME/recording.csv?from=SEQ&to=SEQ``: samples SEQ..to-1 as a trace (docs/reference/
  trace-format.md), one row per drive cycle;
- ``POST /api/axes/NAME/write`` ``{"index": 24705, "sub": 0, "value": 1000}`` (with ``--http-writable``):
  an SDO download of the slave (same checks, same abort codes);
- ``POST /api/axes/NAME/fault`` (with ``--allow-fault-injection``): the MQTT ``fault/set`` command format.

Refusals are JSON ``{"error": ...}`` with a 4xx status (and ``abort_code`` where an SDO would abort); a request
the server cannot parse gets 400 and the connection is closed. Nothing is changed by a refused request.
The periodic job (drain the sample rings, send the messages) runs in the gap after a SYNC's PDOs
(:class:`~virtualaxis.services.cycle_gate.CycleGate`), like the other side channels.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import math
import socket
import struct
import tempfile
import threading
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from virtualaxis.services import listen
from virtualaxis.services.http.frames import FrameLog
from virtualaxis.services.http.ring import COLUMNS, RecordingError, SampleRing

SCOPE_HZ = 60.0  # scope messages per second and stream
STATE_EVERY = 6  # a state message every this many scope ticks (10 per second)
MAX_STREAMS = 64  # event streams open at once (all axes)
STREAM_QUEUE = 120  # messages queued per stream; a stream that falls further behind skips (and is told)
MAX_REQUEST_LINE = 2048
MAX_HEADER_BYTES = 8192
MAX_BODY_BYTES = 4096
READ_TIMEOUT_S = 10.0
DEFAULT_RING_S = 120.0

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
_TYPE_NAMES = {0x1: "BOOL", 0x2: "INT8", 0x3: "INT16", 0x4: "INT32", 0x5: "UINT8", 0x6: "UINT16", 0x7: "UINT32",
               0x8: "REAL32", 0x9: "VISIBLE_STRING", 0xA: "OCTET_STRING", 0xF: "DOMAIN", 0x11: "REAL64",
               0x15: "INT64", 0x1B: "UINT64"}
_ABORT_INVALID_VALUE = 0x06090030
_ABORT_TOO_HIGH = 0x06090031
_ABORT_TOO_LOW = 0x06090032


class HttpRefusal(Exception):
    """A request refused with ``status`` and a JSON body (``error`` plus ``extra``)."""

    def __init__(self, status: int, message: str, **extra: Any):
        super().__init__(message)
        self.status = status
        self.extra = extra


@dataclass
class AxisPage:
    """One axis on the page: name, node id, the drive, its CANopen slave, the fault injector (or None)."""

    name: str
    node_id: int
    drive: Any
    slave: Any
    injector: Any = None
    nmt: Callable[[], str] | None = None
    ring: SampleRing | None = None
    streams: set = field(default_factory=set)
    notes: dict = field(default_factory=dict)  # index -> the EDS [Comments] note


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


class LivePageService:
    """The page's server thread for ``axes``; :meth:`start` binds (raises OSError), :meth:`stop` ends it."""

    def __init__(self, axes: list[AxisPage], *, host: str = "127.0.0.1", port: int = 8080, writable: bool = False,
                 bus: Any = None, frame_log: FrameLog | None = None, gate: Any = None,
                 ring_s: float = DEFAULT_RING_S):
        self.axes = {a.name: a for a in axes}
        self.host, self.port = host, port
        self.writable = writable
        self.bus = bus
        self.frame_log = frame_log
        self.gate = gate
        self.ring_s = ring_s
        self.bound_port: int | None = None
        self.counters = {"requests": 0, "refused": 0, "writes": 0, "writes_refused": 0, "fault_commands": 0,
                         "streams_opened": 0, "messages_skipped": 0, "ticks": 0, "recordings": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._stopping = False
        self._static: dict[str, bytes] = {}

    # ------------------------------------------------------------------ life cycle
    def start(self) -> LivePageService:
        family, kind, proto, _, address = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(64)
        except OSError as exc:
            sock.close()
            raise OSError(f"--http {self.host}:{self.port}: cannot listen ({exc.strerror or exc})") from None
        sock.setblocking(False)
        self._sock = sock
        self.bound_port = sock.getsockname()[1]
        pkg = resources.files("virtualaxis.services.http") / "static"
        self._static = {name: (pkg / name).read_bytes() for name in STATIC_TYPES}
        for ax in self.axes.values():
            ax.ring = SampleRing(ax.drive, self.ring_s).attach()
            ax.notes = eds_notes(getattr(getattr(ax.slave, "od", None), "eds_path", "") or "")
        ready = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(ready,), name="http-page", daemon=True)
        self._thread.start()
        ready.wait(10.0)
        return self

    def stop(self) -> None:
        self._stopping = True
        if self._loop is not None and self._thread is not None:
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(lambda: None)
            self._thread.join(5.0)
        for ax in self.axes.values():
            if ax.ring is not None:
                ax.ring.detach()

    def stats(self) -> dict:
        out = dict(self.counters)
        out["streams_open"] = sum(len(a.streams) for a in self.axes.values())
        out["samples_lost"] = {a.name: a.ring.lost for a in self.axes.values() if a.ring is not None}
        return out

    def _run(self, ready: threading.Event) -> None:
        from virtualaxis.services.threads import short_gil_slices

        short_gil_slices()
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main(ready))
        finally:
            loop.close()

    async def _main(self, ready: threading.Event) -> None:
        server = await asyncio.start_server(self._client, sock=self._sock, limit=MAX_HEADER_BYTES)
        ready.set()
        ticker = asyncio.ensure_future(self._ticker())
        try:
            while not self._stopping:
                await asyncio.sleep(0.05)
        finally:
            ticker.cancel()
            server.close()
            for ax in self.axes.values():
                for q in list(ax.streams):
                    q.put_nowait(None)
            await asyncio.sleep(0.05)
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 1.0)

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
            if self.gate is not None:
                self.gate.wait_next()  # (at most 2 ms: the rest of the communication cycle after the PDOs)
            n += 1
            self.counters["ticks"] = n
            try:
                self._tick(n % STATE_EVERY == 0)
            except Exception:  # noqa: BLE001 - the page never takes serve down; the next tick tries again
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
                self._broadcast(ax, b"state", json.dumps(self.state_of(ax), default=str).encode())

    def _broadcast(self, ax: AxisPage, event: bytes, data: bytes) -> None:
        msg = (event, data)
        for q in ax.streams:
            if q.full():
                self.counters["messages_skipped"] += 1
                continue
            q.put_nowait(msg)

    @staticmethod
    def _scope_message(ax: AxisPage, first: int, end: int) -> bytes:
        times, rows = ax.ring.slice(first, end)
        b64 = base64.b64encode(rows.astype(np.float32).tobytes()).decode("ascii")
        return json.dumps({"seq0": first, "t0": float(times[0]), "dt": ax.ring.cycle_s, "n": end - first,
                           "cols": len(COLUMNS), "b64": b64}).encode()

    def state_of(self, ax: AxisPage) -> dict:
        """The state message of one axis (JSON-ready)."""
        s = ax.drive.state
        faults = sorted(ax.drive.faults, key=lambda f: f.time_s, reverse=True)
        from virtualaxis.drive.faults import fault_info

        warnings = [{"emcy_code": f"0x{code:04X}", "alarm_number": f"A{num:05d}", "text": fault_info(code).text}
                    for code, num in ax.drive.warnings.items()]
        sw = s.statusword
        out = {
            "axis": ax.name, "node_id": ax.node_id, "time_s": s.time_s, "cycles": s.cycles,
            "cia402_state": s.cia402_state, "statusword": sw,
            "statusword_bits": [(sw >> b) & 1 for b in range(16)],
            "controlword": s.controlword, "mode": s.mode, "mode_name": s.mode_name,
            "nmt_state": ax.nmt() if ax.nmt is not None else None,
            "position_actual_m": s.position_actual_m, "position_demand_m": s.position_demand_m,
            "following_error_m": s.following_error_m, "velocity_actual_m_s": s.velocity_actual_m_s,
            "current_a": s.current_a, "torque_nm": s.torque_nm, "dc_link_v": s.dc_link_v,
            "motor_temperature_c": s.motor_temperature_c, "homed": s.homed,
            "fault_active": s.fault_active, "error_code": f"0x{s.error_code:04X}",
            "faults": [f.as_dict() for f in faults], "warnings": warnings,
            "bus_events": self.frame_log.for_node(ax.node_id) if self.frame_log is not None else [],
            "drive_counters": dict(ax.drive.counters),
            "canopen_counters": dict(getattr(ax.slave, "counters", {}) or {}),
            "ring": {"written": ax.ring.written, "oldest": ax.ring.oldest(), "lost": ax.ring.lost,
                     "capacity_s": ax.ring.capacity * ax.ring.cycle_s},
            "fault_injection": sorted(ax.injector.active) if ax.injector is not None else [],
        }
        stats = getattr(self.bus, "stats", None)
        if callable(stats):
            with contextlib.suppress(Exception):
                out["bus"] = stats()
        return out

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
            status, ctype, payload, extra_headers = self._route(method, path, query, headers, body)
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

    def _route(self, method: str, path: str, query: dict, headers: dict, body: bytes):
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
            return _json(200, self.axes_info())
        if path.startswith("/api/axes/"):
            rest = path[len("/api/axes/"):]
            name, sep, what = rest.rpartition("/")
            if not sep:
                raise HttpRefusal(404, f"no route {path[:80]!r} (see /api/axes)")
            ax = self._axis(name)
            if what == "objects":
                self._only(method, "GET")
                return _json(200, self.objects_of(ax))
            if what == "recording.csv":
                self._only(method, "GET")
                return self._recording(ax, query)
            if what == "write":
                self._only(method, "POST")
                if not self.writable:
                    self.counters["writes_refused"] += 1
                    raise HttpRefusal(403, "the page is read-only (serve with --http-writable to write objects)")
                return _json(200, self.write(ax, _json_body(headers, body)))
            if what == "fault":
                self._only(method, "POST")
                return _json(200, self.fault_command(ax, body, headers))
        raise HttpRefusal(404, f"no route {path[:80]!r} (the page is at /, the API under /api/axes)")

    @staticmethod
    def _only(method: str, allowed: str) -> None:
        if method != allowed:
            raise HttpRefusal(405, f"method {method[:16]!r} not allowed here (only {allowed})", allow=allowed)

    def _axis(self, quoted_name: str) -> AxisPage:
        name = urllib.parse.unquote(quoted_name)
        ax = self.axes.get(name)
        if ax is None:
            raise HttpRefusal(404, f"no axis {name[:40]!r} (served: {', '.join(self.axes)})")
        return ax

    def axes_info(self) -> dict:
        from virtualaxis.drive.injection import KINDS

        return {
            "writable": self.writable,
            "columns": list(COLUMNS),
            "axes": [{"name": a.name, "node_id": a.node_id, "cycle_s": a.ring.cycle_s,
                      "fault_injection": bool(a.injector is not None and a.injector.allowed),
                      "force_actuator": getattr(getattr(a.drive.cfg, "actuator", None), "kind", "") == "force"}
                     for a in self.axes.values()],
            "fault_kinds": list(KINDS),
        }

    # ------------------------------------------------------------------ object dictionary
    def objects_of(self, ax: AxisPage) -> dict:
        from virtualaxis.canopen_slave.errors import SdoAbort

        rows = []
        od = ax.slave.od
        with ax.drive.lock:
            for index in sorted(od.objects):
                obj = od.objects[index]
                for sub in sorted(obj.subs):
                    e = obj.subs[sub]
                    row = {"index": f"0x{index:04X}", "sub": sub, "name": e.name, "object": obj.name,
                           "type": _TYPE_NAMES.get(e.data_type, f"0x{e.data_type:X}"), "access": e.access,
                           "low": e.low, "high": e.high, "default": _plain(e.default), "pdo": e.pdo_mappable,
                           "note": ax.notes.get(index, "")}
                    if e.readable:
                        try:
                            row["value"] = _plain(e.decode(ax.slave.sdo_upload(index, sub)))
                        except SdoAbort as exc:
                            row["read_abort"] = f"0x{exc.code:08X}"
                    rows.append(row)
        return {"axis": ax.name, "writable": self.writable, "objects": rows}

    def write(self, ax: AxisPage, data: Any) -> dict:
        """An SDO download of ``{"index", "sub", "value"}`` (HttpRefusal 403 without --http-writable, 400 for a
        malformed request, 422 with the abort code for a refused value)."""
        from virtualaxis.canopen_slave.errors import SdoAbort
        from virtualaxis.canopen_slave.od import type_range

        if not self.writable:
            self.counters["writes_refused"] += 1
            raise HttpRefusal(403, "the page is read-only (serve with --http-writable to write objects)")
        if not isinstance(data, dict):
            raise HttpRefusal(400, f"body must be a JSON object (got {type(data).__name__})")
        unknown = sorted(k for k in data if k not in ("index", "sub", "value"))
        if unknown:
            raise HttpRefusal(400, f"unknown key(s) {', '.join(map(repr, unknown))[:120]} (index, sub, value)")
        index, sub = _index_of(data.get("index"), "index", 0xFFFF), _index_of(data.get("sub", 0), "sub", 0xFF)
        if "value" not in data:
            raise HttpRefusal(400, "value: missing")
        value = data["value"]
        obj = ax.slave.od.objects.get(index)

        def refuse(code: int, message: str) -> HttpRefusal:
            self.counters["writes_refused"] += 1
            return HttpRefusal(422, f"0x{index:04X}:{sub}: {message}", abort_code=f"0x{code:08X}")

        if obj is None:
            raise refuse(0x06020000, "no such object")
        entry = obj.subs.get(sub)
        if entry is None:
            raise refuse(0x06090011, "no such sub-index")
        if entry.fmt is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise refuse(_ABORT_INVALID_VALUE, f"value must be a number (got {type(value).__name__})")
            if entry.fmt in "fd":
                if not math.isfinite(value):
                    raise refuse(_ABORT_INVALID_VALUE, "value must be finite")
                value = float(value)
            else:
                if isinstance(value, float):
                    if not value.is_integer():
                        raise refuse(_ABORT_INVALID_VALUE, f"{entry.name} needs an integer (got {value!r})")
                    value = int(value)
                rng = type_range(entry.data_type)
                if rng is not None and value > rng[1]:
                    raise refuse(_ABORT_TOO_HIGH, f"{value} > {rng[1]} (type range)")
                if rng is not None and value < rng[0]:
                    raise refuse(_ABORT_TOO_LOW, f"{value} < {rng[0]} (type range)")
            try:
                payload = entry.encode(value)
            except (struct.error, OverflowError) as exc:
                raise refuse(_ABORT_INVALID_VALUE, str(exc)) from None
        elif isinstance(value, str):
            payload = entry.encode(value)
        else:
            raise refuse(_ABORT_INVALID_VALUE, f"value must be a string for {entry.name}")
        try:
            with ax.drive.lock:
                ax.slave.sdo_download(index, sub, payload)
                now = entry.decode(ax.slave.sdo_upload(index, sub)) if entry.readable else None
        except SdoAbort as exc:
            raise refuse(exc.code, exc.message or str(exc)) from None
        self.counters["writes"] += 1
        return {"ok": True, "index": f"0x{index:04X}", "sub": sub, "value": _plain(now)}

    def fault_command(self, ax: AxisPage, body: bytes, headers: dict) -> dict:
        from virtualaxis.services.mqtt import apply_fault_command, parse_fault_command

        _check_json_type(headers)
        if ax.injector is None or not ax.injector.allowed:
            raise HttpRefusal(403, "fault injection is off (serve with --allow-fault-injection)",
                              abort_code="0x08000022")
        command, refusal = parse_fault_command(body)
        if refusal is not None:
            raise HttpRefusal(400, refusal.get("error", "malformed fault command"))
        self.counters["fault_commands"] += 1
        result = apply_fault_command(ax.injector, command)
        if not result.get("ok"):
            raise HttpRefusal(422, result.get("error", "refused"),
                              **{k: v for k, v in result.items() if k not in ("error",)})
        return result

    # ------------------------------------------------------------------ recording
    def _recording(self, ax: AxisPage, query: dict):
        from virtualaxis.sim.trace_io import TraceWriter

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
        force = getattr(getattr(ax.drive.cfg, "actuator", None), "kind", "") == "force"
        cols = {"pos_cmd": 0, "pos_fb": 1, "vel_meas": 3, ("force_drive" if force else "torque_meas"): 4,
                "current_q": 5, "following_error": 2, "statusword": 6}
        data = {"t": times, **{c: rows[:, j] for c, j in cols.items()}}
        with tempfile.TemporaryDirectory(prefix="virtualaxis-page-") as tmp:
            path = Path(tmp) / "recording.csv"
            with TraceWriter(path, list(cols)) as w:
                w.write(data)
            payload = path.read_bytes()
        self.counters["recordings"] += 1
        fname = f"{_safe_file_part(ax.name)}-{bounds[0]}-{bounds[1]}.csv"
        return 200, "text/csv; charset=utf-8", payload, {"Content-Disposition": f'attachment; filename="{fname}"'}

    # ------------------------------------------------------------------ event stream
    async def _stream(self, ax: AxisPage, writer: asyncio.StreamWriter) -> None:
        if sum(len(a.streams) for a in self.axes.values()) >= MAX_STREAMS:
            self.counters["refused"] += 1
            self._respond_json(writer, 503, {"error": f"{MAX_STREAMS} event streams open already (close a tab)"})
            await _drain(writer)
            return
        q: asyncio.Queue = asyncio.Queue(STREAM_QUEUE)
        writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n"
                     b"Connection: keep-alive\r\nX-Content-Type-Options: nosniff\r\n\r\n"
                     b"retry: 1000\n\n")
        q.put_nowait((b"state", json.dumps(self.state_of(ax), default=str).encode()))
        ax.streams.add(q)
        self.counters["streams_opened"] += 1
        try:
            while True:
                msg = await q.get()
                if msg is None:
                    return
                writer.write(b"event: " + msg[0] + b"\ndata: " + msg[1] + b"\n\n")
                await writer.drain()
        finally:
            ax.streams.discard(q)

    async def _websocket(self, ax: AxisPage, headers: dict, reader: asyncio.StreamReader,
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
        q.put_nowait((b"state", json.dumps(self.state_of(ax), default=str).encode()))
        ax.streams.add(q)
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
            ax.streams.discard(q)

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


def _plain(v: Any) -> Any:
    if isinstance(v, (bytes, bytearray)):
        return v.hex(" ")
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


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


def _index_of(v: Any, key: str, high: int) -> int:
    """An object index / sub-index given as a number or a string ("0x6081", "24705")."""
    if isinstance(v, str):
        try:
            v = int(v, 0)
        except ValueError:
            raise HttpRefusal(400, f"{key}: {v[:20]!r} is not a number") from None
    if isinstance(v, bool) or not isinstance(v, int):
        raise HttpRefusal(400, f"{key}: must be an integer or a string like \"0x6081\" (got {type(v).__name__})")
    if not 0 <= v <= high:
        raise HttpRefusal(400, f"{key}: must be 0..0x{high:X} (got {v})")
    return v


def _safe_file_part(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)[:40] or "axis"
