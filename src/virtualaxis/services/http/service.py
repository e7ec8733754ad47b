"""serve's side of the live page (docs/live-page.md): the page's server runs in a process of its own.

:class:`LivePageService` binds the page's address (an error names ``--http``), creates the shared-memory
segment (ring.py) and starts the **server process** (server.py: a plain child interpreter, as the Modbus,
MQTT and OPC UA servers; it imports neither the drive nor numba), handing it the listening socket and one end
of a socket pair. What it costs serve's process:

- the drive's **cycle hook** per axis (ring.py: three ``pack_into`` per cycle, no allocation of its own);
- the **state message** of each axis (JSON) into the segment ten times a second while the axis has a live
  stream open, once a second otherwise. With ``run_in_gap`` (``Runtime.run_in_gap``; serve passes it at real-time
  priority) a timer thread hands the work to the runtime thread, which does it in the gap before a drive cycle,
  so that the drive's thread never waits for another thread's interpreter lock (a priority inversion at
  real-time priority). Without, the timer thread does it itself, in the gap after a SYNC's PDOs (cycle_gate.py),
  on the other core while the drive runs;
- a **bridge thread**: the requests the server process forwards -- the object dictionary with its values,
  object writes (``--http-writable``: the SDO download's checks and abort codes) and fault-injection commands
  (``--http-writable`` and ``--allow-fault-injection``) -- applied under the drive's lock, i.e. between two
  cycles, and answered.

The server process is serve's child (child.py): it ends on the socket pair's EOF, i.e. with serve even if serve
is killed. If it ends on its own, serve prints one warning line and goes on serving CANopen (``server_process``
in the stats).
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import socket
import struct
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from virtualaxis.services.child import ChildProcess
from virtualaxis.services.http.frames import FrameLog
from virtualaxis.services.http.ring import COLUMNS, STATE_BYTES, PageBlock, segment_size
from virtualaxis.services.http.server import HttpRefusal, check_fault_injection, eds_notes, parse_index

STATE_PERIOD_S = 0.1  # state messages of an axis with a live stream open
IDLE_STATE_EVERY = 10  # ... and every this many periods without one
START_TIMEOUT_S = 30.0
_TYPE_NAMES = {0x1: "BOOL", 0x2: "INT8", 0x3: "INT16", 0x4: "INT32", 0x5: "UINT8", 0x6: "UINT16", 0x7: "UINT32",
               0x8: "REAL32", 0x9: "VISIBLE_STRING", 0xA: "OCTET_STRING", 0xF: "DOMAIN", 0x11: "REAL64",
               0x15: "INT64", 0x1B: "UINT64"}
_ABORT_INVALID_VALUE = 0x06090030
_ABORT_TOO_HIGH = 0x06090031
_ABORT_TOO_LOW = 0x06090032
_REAL32_MAX = 3.4028234663852886e38


@dataclass
class AxisPage:
    """One axis on the page: name, node id, the drive, its CANopen slave, the fault injector (or None)."""

    name: str
    node_id: int
    drive: Any
    slave: Any
    injector: Any = None
    nmt: Callable[[], str] | None = None
    block: PageBlock | None = None
    notes: dict = field(default_factory=dict)  # index -> the EDS [Comments] note


class LivePageService:
    """The live page of ``axes``: :meth:`start` binds (raises OSError naming ``--http``) and starts the server
    process, :meth:`stop` ends it (module doc)."""

    def __init__(self, axes: list[AxisPage], *, host: str = "127.0.0.1", port: int = 8080, writable: bool = False,
                 bus: Any = None, frame_log: FrameLog | None = None, gate: Any = None, ring_s: float = 120.0,
                 run_in_gap: Callable[[Callable[[], None]], None] | None = None):
        self.axes = list(axes)
        self.host, self.port = host, port
        self.writable = writable
        self.bus = bus
        self.frame_log = frame_log
        self.gate = gate
        self.run_in_gap = run_in_gap
        self._queued: set[int] = set()  # axes whose state message waits for the runtime thread
        self.ring_s = ring_s
        self.bound_port: int | None = None
        self.counters = {"writes": 0, "writes_refused": 0, "fault_commands": 0, "state_messages": 0,
                         "state_errors": 0}
        self.server_counters: dict = {}  # as last reported by the server process
        self._shm = None
        self._child = ChildProcess(f"--http {host}:{port}", "the live page's server", "the live page")
        self._stop = threading.Event()
        self._state: threading.Thread | None = None

    # ------------------------------------------------------------------ life cycle
    def start(self) -> LivePageService:
        from multiprocessing import shared_memory

        from virtualaxis.services.threads import short_gil_slices

        where = f"--http {self.host}:{self.port}"
        family, kind, proto, _, address = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(64)
        except OSError as exc:
            sock.close()
            raise OSError(f"{where}: cannot listen ({exc.strerror or exc})") from None
        self.bound_port = sock.getsockname()[1]
        short_gil_slices()
        self._shm = shared_memory.SharedMemory(create=True, size=segment_size(len(self.axes)))
        self._shm.buf[:] = b"\x00" * self._shm.size
        for i, ax in enumerate(self.axes):
            ax.block = PageBlock(self._shm.buf, i)
            ax.notes = eds_notes(getattr(getattr(ax.slave, "od", None), "eds_path", "") or "")
            with ax.drive.lock:
                ax.block.set_units(ax.drive)
            self._publish_state(ax)
        spec = {"shm": self._shm.name, "writable": self.writable, "ring_s": self.ring_s, "info": self.axes_info(),
                "axes": [{"name": a.name, "cycle_s": float(a.drive.cycle_s), "force_actuator": _force(a),
                          "fault_injection_allowed": _injection_allowed(a)} for a in self.axes]}
        try:  # (the server process holds the listening socket from now on)
            self._child.start("virtualaxis.services.http.server:server_child", ("init", spec), START_TIMEOUT_S,
                              pass_fds=(sock.detach(),))
        except OSError:
            self.stop()
            raise
        for ax in self.axes:
            ax.drive.add_cycle_hook(ax.block.hook)
        self._child.serve(self._handle, "virtualaxis-http-bridge")
        self._state = threading.Thread(target=self._state_loop, name="virtualaxis-http-state", daemon=True)
        self._state.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        for ax in self.axes:
            if ax.block is not None:
                ax.drive.remove_cycle_hook(ax.block.hook)
        if self._state is not None:
            self._state.join(timeout_s)
        self._child.stop(timeout_s)
        for ax in self.axes:
            ax.block = None
        if self._shm is not None:
            with contextlib.suppress(BufferError):
                self._shm.close()
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()
            self._shm = None

    @property
    def server_pid(self) -> int | None:
        """The process id of the page's server process (None before start)."""
        return self._child.pid

    @property
    def server_process(self) -> str:
        """not started, running, stopped, failed (why), or ended (exit code N)."""
        return self._child.status

    def stats(self) -> dict:
        out = dict(self.server_counters)
        for k, v in self.counters.items():
            out[k] = out.get(k, 0) + v
        out.update(server_pid=self.server_pid, server_process=self.server_process)
        return out

    # ------------------------------------------------------------------ the state thread
    def _state_loop(self) -> None:
        tick = 0
        run_in_gap = self.run_in_gap
        while not self._stop.wait(STATE_PERIOD_S):
            if run_in_gap is None and self.gate is not None:
                self.gate.wait_next()  # (at most 2 ms: the rest of the communication cycle after the PDOs)
            tick += 1
            for i, ax in enumerate(self.axes):
                if ax.block is None or (not ax.block.clients() and tick % IDLE_STATE_EVERY):
                    continue
                if run_in_gap is None:
                    self._publish_state(ax)
                elif i not in self._queued:  # (one waiting per axis: a slow runtime gets no backlog)
                    self._queued.add(i)
                    run_in_gap(functools.partial(self._publish_queued, i))

    def _publish_queued(self, i: int) -> None:
        """The runtime thread's part: one axis' state message (skipped once the page stopped)."""
        self._queued.discard(i)
        ax = self.axes[i]
        if ax.block is not None and not self._stop.is_set():
            self._publish_state(ax)

    def _publish_state(self, ax: AxisPage) -> None:
        try:
            with ax.drive.lock:
                ax.block.set_units(ax.drive)
            state = self.state_of(ax)
            msg = json.dumps(state, default=str).encode()
            while len(msg) > STATE_BYTES and (state["faults"] or state["bus_events"]):  # (the oldest go first)
                for key in ("bus_events", "faults"):
                    if state[key]:
                        state[key] = state[key][: len(state[key]) // 2]
                msg = json.dumps(state, default=str).encode()
            ax.block.set_state(msg)
            self.counters["state_messages"] += 1
        except Exception:  # noqa: BLE001 - the page never takes serve down; the next period tries again
            self.counters["state_errors"] += 1
            if self.counters["state_errors"] == 1:
                import logging

                logging.getLogger("virtualaxis.services.http").exception("live page state failed")

    def state_of(self, ax: AxisPage) -> dict:
        """The state message of one axis (JSON-ready; the server process adds its ring's figures)."""
        from virtualaxis.drive.faults import fault_info

        s = ax.drive.state
        faults = sorted(ax.drive.faults, key=lambda f: f.time_s, reverse=True)
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
            "fault_injection": sorted(ax.injector.active) if ax.injector is not None else [],
        }
        stats = getattr(self.bus, "stats", None)
        if callable(stats):
            with contextlib.suppress(Exception):
                out["bus"] = stats()
        return out

    def axes_info(self) -> dict:
        """``GET /api/axes``: the axes, the scope's columns, whether the page may write objects (``writable``) and
        inject faults on an axis (``fault_injection``: serve runs with both ``--http-writable`` and
        ``--allow-fault-injection``)."""
        from virtualaxis.drive.injection import KINDS

        return {
            "writable": self.writable,
            "columns": list(COLUMNS),
            "axes": [{"name": a.name, "node_id": a.node_id, "cycle_s": float(a.drive.cycle_s),
                      "fault_injection": self.writable and _injection_allowed(a),
                      "force_actuator": _force(a)}
                     for a in self.axes],
            "fault_kinds": list(KINDS),
        }

    # ------------------------------------------------------------------ the bridge thread
    def _handle(self, msg: tuple) -> tuple | None:
        """A message of the server process: its counters, or a request on a live drive (answered)."""
        kind = msg[0]
        if kind == "stats":
            self.server_counters = msg[1]
        elif kind in ("objects", "write", "fault"):
            rid, axis = msg[1], self.axes[msg[2]]
            try:
                if kind == "objects":
                    reply = ("ok", self.objects_of(axis))
                elif kind == "write":
                    reply = ("ok", self.write(axis, msg[3]))
                else:
                    reply = ("ok", self.fault_command(axis, msg[3]))
            except HttpRefusal as exc:
                reply = ("refused", exc.status, str(exc), exc.extra)
            except Exception as exc:  # noqa: BLE001 - the client gets a 500, serve goes on
                reply = ("refused", 500, f"internal error: {type(exc).__name__}: {exc}", {})
            return "reply", rid, reply
        return None

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
        index, sub = parse_index(data.get("index"), "index", 0xFFFF), parse_index(data.get("sub", 0), "sub", 0xFF)
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
        type_name = _TYPE_NAMES.get(entry.data_type, f"0x{entry.data_type:X}")

        def out_of_range(v: float) -> HttpRefusal:
            above = v > 0
            return refuse(_ABORT_TOO_HIGH if above else _ABORT_TOO_LOW,
                          f"{entry.name}: {_num(v)} is {'above' if above else 'below'} its range "
                          f"{_range_text(entry, type_name)}")

        if entry.fmt is not None:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise refuse(_ABORT_INVALID_VALUE, f"{entry.name}: value must be a number (got "
                             f"{type(value).__name__})")
            if isinstance(value, float) and math.isinf(value):  # (a JSON number beyond a float, e.g. 1e400)
                raise out_of_range(value)
            if isinstance(value, float) and math.isnan(value):
                raise refuse(_ABORT_INVALID_VALUE, f"{entry.name}: value must be finite")
            if entry.fmt in "fd":
                value = float(value)
                try:
                    entry.encode(value)
                except OverflowError:  # (beyond REAL32)
                    raise out_of_range(value) from None
            else:
                if isinstance(value, float):
                    if not value.is_integer():
                        raise refuse(_ABORT_INVALID_VALUE, f"{entry.name} needs an integer (got {value!r})")
                    value = int(value)
                rng = type_range(entry.data_type)
                if rng is not None and not rng[0] <= value <= rng[1]:
                    raise out_of_range(data["value"])  # (as given: 1e+39, not its digits)
            try:
                payload = entry.encode(value)
            except (struct.error, OverflowError) as exc:
                raise refuse(_ABORT_INVALID_VALUE, f"{entry.name}: {exc}") from None
        elif isinstance(value, str):
            payload = entry.encode(value)
        else:
            raise refuse(_ABORT_INVALID_VALUE, f"value must be a string for {entry.name}")
        try:
            with ax.drive.lock:
                ax.slave.sdo_download(index, sub, payload)
                now = entry.decode(ax.slave.sdo_upload(index, sub)) if entry.readable else None
        except SdoAbort as exc:
            message = exc.message or str(exc)
            if exc.code in (_ABORT_TOO_HIGH, _ABORT_TOO_LOW) and not exc.message:
                message = (f"{entry.name}: {_num(value)} is {'above' if exc.code == _ABORT_TOO_HIGH else 'below'} its "
                           f"range {_range_text(entry, type_name)}")
            raise refuse(exc.code, message) from None
        self.counters["writes"] += 1
        return {"ok": True, "index": f"0x{index:04X}", "sub": sub, "value": _plain(now)}

    def fault_command(self, ax: AxisPage, body: bytes) -> dict:
        """A fault-injection command as the server process checked and forwarded it (JSON, MQTT ``fault/set``'s
        format); HttpRefusal 403 unless serve runs with both ``--http-writable`` and ``--allow-fault-injection``
        (serve's own check: it holds the flags), 400 for a malformed command, 422 if refused."""
        from virtualaxis.services.mqtt import apply_fault_command, parse_fault_command

        check_fault_injection(self.writable, _injection_allowed(ax))
        command, refusal = parse_fault_command(body)
        if refusal is not None:
            raise HttpRefusal(400, refusal.get("error", "malformed fault command"))
        self.counters["fault_commands"] += 1
        result = apply_fault_command(ax.injector, command)
        if not result.get("ok"):
            raise HttpRefusal(422, result.get("error", "refused"),
                              **{k: v for k, v in result.items() if k not in ("error",)})
        return result


def _force(ax: AxisPage) -> bool:
    return getattr(getattr(ax.drive.cfg, "actuator", None), "kind", "") == "force"


def _plain(v: Any) -> Any:
    if isinstance(v, (bytes, bytearray)):
        return v.hex(" ")
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def _injection_allowed(ax: AxisPage) -> bool:
    """Whether serve runs the axis with ``--allow-fault-injection``."""
    return bool(ax.injector is not None and ax.injector.allowed)


def _range_text(entry: Any, type_name: str) -> str:
    """The range of an entry's values: its EDS limits where it has them, else its data type's."""
    from virtualaxis.canopen_slave.od import type_range

    rng = type_range(entry.data_type)
    if entry.fmt == "f":
        rng = (-_REAL32_MAX, _REAL32_MAX)
    elif entry.fmt == "d":
        rng = (-sys.float_info.max, sys.float_info.max)
    low = entry.low if entry.low is not None else rng[0] if rng else None
    high = entry.high if entry.high is not None else rng[1] if rng else None
    text = f"{'' if low is None else _num(low)} .. {'' if high is None else _num(high)}"
    return text + ("" if entry.low is not None or entry.high is not None else f" ({type_name})")


def _num(v: float) -> str:
    """A number in a message: an integer in full, a float as Python writes it back (``1e+39``, ``0.1``) or, when
    integral, without ``.0`` (``2000``)."""
    if isinstance(v, int) or not math.isfinite(v) or abs(v) >= 1e16 or not v.is_integer():
        return repr(v)
    return str(int(v))
