"""OPC UA server of the served axes (asyncua): ``virtualaxis serve --opcua HOST:PORT`` (docs/opcua.md).

Address space (namespace :data:`NAMESPACE_URI`, string node ids ``VirtualAxis.<axis>.<folder>.<name>``)::

    Objects/VirtualAxis/<axis>/            (object; emits DriveFaultEventType events)
        NodeId                             (property: CANopen node id)
        State/          CiA402State, Statusword, Controlword, ModeOfOperation, ModeName, NmtState, Homed,
                        TargetReached, Warning, DriveTime
        ActualValues/   Position [m], Velocity [m/s], FollowingError [m], Current [A], Torque [N m],
                        MotorTemperature [C]  (AnalogItemType: EngineeringUnits (UNECE), EURange)
        Faults/         FaultActive, ErrorCode, ActiveFault, AlarmNumber, FaultBuffer, FaultCodes
        Parameters/     one AnalogItemType variable per drive parameter (SI units, Drive.parameter_names()),
                        LastWriteResult
        Methods/        InjectFault(Kind, Duty, PeriodS, Magnitude), ClearFault(Kind)  (--allow-fault-injection)

Where the work runs: the asyncua server is a **server process** of its own (:class:`ServerProcess`, a child
interpreter of serve joined by a socket pair; it imports neither the drive nor numba), so that its clients cost
that process the CPU and the interpreter lock, not serve's. In serve (:class:`OpcuaService`):

- a **sampler thread** takes one ``drive.state`` per axis every :data:`SAMPLE_PERIOD_S` (in the gap after a
  SYNC's PDOs when a cycle gate is given, see cycle_gate.py) and sends the node values as one compact batch
  (plain tuples; a batch equal to the last one is not sent), the parameters and ranges every
  :data:`PARAMETER_PERIOD_S`; the server process applies the newest batch and replaces one it has not taken up
  yet (counted: ``samples_replaced``): the drive never waits for the server;
- fault events come from a drive observer (cheap, under the drive's lock) as plain records in the next batch;
  the server process emits the OPC UA events;
- a **bridge thread** applies the writes and method calls the server process forwards, and takes its counters.

The server process is serve's child (child.py): it ends on the socket's EOF, i.e. with serve even if serve is
killed; if it ends on its own, serve prints one warning line and goes on serving CANopen (``server_process`` in
the stats).

Client writes go only to ``Parameters/*`` and only with ``writable``: each is checked and applied (in serve) by
``Drive.set_parameter`` (the checks of an SDO download); a refusal answers the SDO abort code's OPC UA status
(:data:`STATUS_OF_ABORT`) and leaves the value unchanged. Every other node of the namespace is read-only
(``BadNotWritable``).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import itertools
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from virtualaxis.services import listen
from virtualaxis.services.child import ChildProcess, ParentLink, enter_child
from virtualaxis.services.threads import short_gil_slices

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive

NAMESPACE_URI = "urn:virtualaxis:opcua"
APPLICATION_URI = "urn:virtualaxis:server"
DEFAULT_ADDRESS = ("127.0.0.1", 4840)
ENDPOINT_PATH = "/virtualaxis"
SAMPLE_PERIOD_S = 0.01  # drive state -> node values, 100 per second
PARAMETER_PERIOD_S = 0.5  # parameters (also changed by SDO, Modbus) and the EURange that follow them
EXTRA_HINT = "pip install 'virtualaxis[opcua]'"

# UNECE Recommendation 20 common codes (OPC UA Part 8: UnitId = the code's characters as a big-endian integer)
UNECE_NAMESPACE = "http://www.opcfoundation.org/UA/units/un/cefact"
UNITS: dict[str, tuple[str, str, str]] = {  # unit -> (common code, display name, description)
    "m": ("MTR", "m", "metre"),
    "m/s": ("MTS", "m/s", "metre per second"),
    "m/s^2": ("MSK", "m/s²", "metre per second squared"),
    "A": ("AMP", "A", "ampere"),
    "N m": ("NU", "N·m", "newton metre"),
    "N": ("NEW", "N", "newton"),
    "C": ("CEL", "°C", "degree Celsius"),
    "ms": ("C26", "ms", "millisecond"),
    "s": ("SEC", "s", "second"),
    "1": ("C62", "1", "one"),
}


def unece_unit_id(code: str) -> int:
    """The UnitId of a UNECE common code (e.g. "MTR" -> 5067858)."""
    out = 0
    for ch in code:
        out = out << 8 | ord(ch)
    return out


def parameter_unit(name: str, doc: str) -> str | None:
    """The unit of a drive parameter from its name (``_m``, ``_m_s``, ``_nm``...) or its document's ``[...]``."""
    for suffix, unit in (("_m_s3", None), ("_m_s2", "m/s^2"), ("_m_s", "m/s"), ("_m", "m"), ("_nm", "N m"),
                         ("_a", "A"), ("_ms", "ms"), ("_c", "C"), ("_n", "N")):
        if name.endswith(suffix):
            return unit
    if "[1]" in doc:
        return "1"
    return None


# SDO abort code -> OPC UA status code name of a refused parameter write
STATUS_OF_ABORT: dict[int, str] = {
    0x06090030: "BadOutOfRange",  # value invalid (not an allowed value of the object)
    0x06090031: "BadOutOfRange",  # value too high
    0x06090032: "BadOutOfRange",  # value too low
    0x06010002: "BadNotWritable",  # read-only object
    0x08000022: "BadInvalidState",  # not in the drive's present state
    0x06020000: "BadNodeIdUnknown",  # no such object
    0x06070010: "BadTypeMismatch",  # data type / length
}


# ============================================================================================== settings
class OpcuaSettingsError(ValueError):
    """A bad ``--opcua*`` option or users file (the message names it)."""


@dataclass
class OpcuaSettings:
    host: str = DEFAULT_ADDRESS[0]
    port: int = DEFAULT_ADDRESS[1]
    writable: bool = False
    users: dict[str, str] | None = None  # username -> password; None: anonymous
    cert_file: str | None = None  # server certificate (PEM or DER): Basic256Sha256 SignAndEncrypt only
    key_file: str | None = None
    allow_fault_injection: bool = False
    eds_path: str | None = None  # EURange of the parameters from its LowLimit / HighLimit

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}{ENDPOINT_PATH}"


def parse_address(text: str | None, option: str = "--opcua") -> tuple[str, int]:
    """``HOST:PORT`` (or ``[v6]:PORT``, ``HOST``, ``:PORT``); default 127.0.0.1:4840."""
    return listen.parse_host_port(text, option=option, default=DEFAULT_ADDRESS, error=OpcuaSettingsError)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listen(host: str, port: int) -> None:
    """Raise :class:`OpcuaSettingsError` naming ``--opcua`` if a server could not listen on ``host:port``."""
    listen.check_listen(host, port, option="--opcua", error=OpcuaSettingsError)


def load_users(path: str) -> dict[str, str]:
    """The ``[users]`` table of a TOML file: ``name = "password"`` (at least one)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    p = Path(path)
    if not p.is_file():
        raise OpcuaSettingsError(f"--opcua-users {path}: " + ("not a file" if p.exists() else "file not found"))
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise OpcuaSettingsError(f"--opcua-users {path}: cannot read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise OpcuaSettingsError(f"--opcua-users {path}: not valid TOML ({exc})") from None
    unknown = sorted(set(data) - {"users"})
    if unknown:
        raise OpcuaSettingsError(f"--opcua-users {path}: unknown key(s) {', '.join(unknown)} (expected a [users] "
                                 "table of name = \"password\")")
    users = data.get("users")
    if not isinstance(users, dict) or not users:
        raise OpcuaSettingsError(f"--opcua-users {path}: [users]: needs at least one name = \"password\"")
    for name, password in users.items():
        if not isinstance(password, str) or not password:
            raise OpcuaSettingsError(f"--opcua-users {path}: users.{name}: the password must be a non-empty "
                                     "string")
    return dict(users)


def check_certificate(cert_file: str, key_file: str) -> None:
    """The certificate (PEM or DER) and its private key (PEM or DER, unencrypted) load and belong together."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    def load(path: str, option: str, pem, der):
        try:
            data = Path(path).read_bytes()
        except OSError as exc:
            raise OpcuaSettingsError(f"{option} {path}: cannot read ({exc.strerror or exc})") from None
        for loader in (pem, der):
            try:
                return loader(data)
            except (ValueError, TypeError):
                continue
        raise OpcuaSettingsError(f"{option} {path}: not a PEM or DER " + ("certificate" if option == "--opcua-cert"
                                                                           else "unencrypted private key"))

    cert = load(cert_file, "--opcua-cert", x509.load_pem_x509_certificate, x509.load_der_x509_certificate)
    key = load(key_file, "--opcua-key", lambda d: serialization.load_pem_private_key(d, None),
               lambda d: serialization.load_der_private_key(d, None))
    spki = (serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    if cert.public_key().public_bytes(*spki) != key.public_key().public_bytes(*spki):
        raise OpcuaSettingsError(f"--opcua-key {key_file}: not the private key of --opcua-cert {cert_file}")


def prepare(args) -> OpcuaSettings | None:
    """``--opcua*`` options of ``serve`` -> settings (None without --opcua); raises OpcuaSettingsError."""
    given = [opt for opt, v in (("--opcua-writable", args.opcua_writable), ("--opcua-users", args.opcua_users),
                                ("--opcua-cert", args.opcua_cert), ("--opcua-key", args.opcua_key)) if v]
    if args.opcua is None:
        if given:
            raise OpcuaSettingsError(f"{' / '.join(given)} need(s) --opcua")
        return None
    try:
        import asyncua  # noqa: F401
    except ImportError:
        raise OpcuaSettingsError(f"--opcua needs the asyncua package, not installed here ({EXTRA_HINT})") from None
    host, port = parse_address(args.opcua)
    st = OpcuaSettings(host, port, writable=bool(args.opcua_writable),
                       allow_fault_injection=bool(getattr(args, "allow_fault_injection", False)),
                       eds_path=getattr(args, "eds", None))
    if args.opcua_users:
        st.users = load_users(args.opcua_users)
    if bool(args.opcua_cert) != bool(args.opcua_key):
        raise OpcuaSettingsError("--opcua-cert and --opcua-key go together (the server's certificate and its "
                                 "private key)")
    for opt, path in (("--opcua-cert", args.opcua_cert), ("--opcua-key", args.opcua_key)):
        if path and not Path(path).is_file():
            raise OpcuaSettingsError(f"--opcua-{opt[8:]} {path}: " + ("not a file" if Path(path).exists()
                                                                       else "file not found"))
    if args.opcua_cert:
        check_certificate(args.opcua_cert, args.opcua_key)
    st.cert_file, st.key_file = args.opcua_cert, args.opcua_key
    if st.users is None and not is_loopback(host):
        raise OpcuaSettingsError(f"--opcua {args.opcua}: anonymous access is served on loopback addresses only; "
                                 "give --opcua-users FILE to serve on another address")
    check_listen(host, port)
    return st


# ============================================================================================== the server
@dataclass
class AxisSource:
    """One served axis: name, node id, drive, NMT state getter, fault injector (or None)."""

    name: str
    node_id: int
    drive: Drive
    nmt_state: Callable[[], str] | None = None
    injector: Any = None
    events: deque = field(default_factory=lambda: deque(maxlen=1024))  # (kind, DriveState, FaultRecord | None)
    events_dropped: int = 0

    def nmt(self) -> str:
        if self.nmt_state is None:
            return "UNKNOWN"
        try:
            return str(self.nmt_state())
        except Exception:  # noqa: BLE001 - a diagnostic field
            return "UNKNOWN"


STATE_VARS = (  # name, variant type name, description
    ("CiA402State", "String", "CiA 402 state (statusword 0x6041)"),
    ("Statusword", "UInt16", "statusword 0x6041"),
    ("Controlword", "UInt16", "controlword 0x6040"),
    ("ModeOfOperation", "SByte", "modes of operation display 0x6061"),
    ("ModeName", "String", "mode of operation (e.g. CSP)"),
    ("NmtState", "String", "CANopen NMT state"),
    ("Homed", "Boolean", "the axis is referenced"),
    ("TargetReached", "Boolean", "statusword bit 10"),
    ("Warning", "Boolean", "statusword bit 7"),
    ("DriveTime", "Double", "drive (simulation) time [s]"),
)
ACTUAL_VARS = (  # name, unit, DriveState field, description
    ("Position", "m", "position_actual_m", "position actual value 0x6064 [m]; EURange: software limits 0x607D"),
    ("Velocity", "m/s", "velocity_actual_m_s", "velocity actual value 0x606C [m/s]; EURange: +-0x607F"),
    ("FollowingError", "m", "following_error_m", "following error 0x60F4 [m]; EURange: +-window 0x6065"),
    ("Current", "A", "current_a", "q current [A]; EURange: +-max current 0x6073"),
    ("Torque", "N m", "torque_nm", "torque actual value 0x6077 [N m]; EURange: +-max torque 0x6072"),
    ("MotorTemperature", "C", "motor_temperature_c", "motor temperature [C]; EURange: 0..fault threshold"),
)
ACTUAL_RANGES = {  # actual value -> its EURange from the drive's parameters (SI)
    "Position": lambda p: (p["software_limit_min_m"], p["software_limit_max_m"]),
    "Velocity": lambda p: (-p["max_profile_velocity_m_s"], p["max_profile_velocity_m_s"]),
    "FollowingError": lambda p: (-p["following_error_tolerance_m"], p["following_error_tolerance_m"]),
    "Current": lambda p: (-p["current_limit_a"], p["current_limit_a"]),
    "Torque": lambda p: (-p["torque_limit_nm"], p["torque_limit_nm"]),
    "MotorTemperature": lambda p: (0.0, p["motor_temperature_fault_c"]),
}
FAULT_VARS = (
    ("FaultActive", "Boolean", "the drive is in FAULT or FAULT REACTION ACTIVE"),
    ("ErrorCode", "UInt16", "error code 0x603F (EMCY code of the active fault)"),
    ("ActiveFault", "String", "the newest unacknowledged fault: code, number and text ('' without)"),
    ("AlarmNumber", "UInt16", "alarm number 0x2031 (0: none)"),
    ("FaultBuffer", "String[]", "fault buffer, newest first: 'EMCY Fnnnnn value text (active|acknowledged)'"),
    ("FaultCodes", "UInt16[]", "EMCY codes of the fault buffer, newest first (r0945)"),
)
DTYPE_VARIANT = {"u8": "Byte", "i8": "SByte", "u16": "UInt16", "i16": "Int16", "u32": "UInt32", "i32": "Int32",
                 "f32": "Double"}
EVENT_FIELDS = (  # DriveFaultEventType properties
    ("Axis", "String"), ("Kind", "String"), ("EmcyCode", "UInt16"), ("FaultNumber", "UInt32"),
    ("FaultValue", "Int32"), ("Injected", "Boolean"), ("CiA402State", "String"),
)
EVENT_SEVERITY = {"fault": 800, "fault_cleared": 300, "alarm": 500, "alarm_cleared": 200}


def fault_line(f) -> str:
    return (f"0x{f.emcy_code:04X} F{f.fault_number:05d} {f.value} {f.text} "
            f"({'acknowledged' if f.acknowledged else 'active'})")


def state_values(s, nmt: str) -> tuple:
    """The values of :data:`STATE_VARS` (in order) of a DriveState."""
    return (s.cia402_state, s.statusword, s.controlword, s.mode, s.mode_name, nmt, bool(s.homed),
            bool(s.target_reached), bool(s.warning), float(s.time_s))


def actual_values(s) -> tuple:
    """The values of :data:`ACTUAL_VARS` (in order) of a DriveState."""
    return tuple(float(getattr(s, attr)) for _name, _unit, attr, _desc in ACTUAL_VARS)


def fault_values(s) -> tuple:
    """The values of :data:`FAULT_VARS` (in order) of a DriveState."""
    active = [f for f in s.faults if not f.acknowledged] if s.fault_active else []
    text = f"0x{active[0].emcy_code:04X} F{active[0].fault_number:05d} {active[0].text}" if active else ""
    return (bool(s.fault_active), int(s.error_code), text, int(s.alarm_number), [fault_line(f) for f in s.faults],
            [int(f.emcy_code) for f in s.faults])


def actual_ranges(params: dict[str, float]) -> list[tuple[float, float]]:
    """The EURange of each of :data:`ACTUAL_VARS` (in order) from the drive's parameters."""
    return [tuple(float(v) for v in ACTUAL_RANGES[name](params)) for name, *_ in ACTUAL_VARS]


def parameter_node_value(value: float, vt: str):
    return value if vt == "Double" else int(round(value))


def event_record(kind: str, s, rec) -> dict:
    """A fault / alarm event of a DriveState as the plain fields of a DriveFaultEventType event."""
    if kind.startswith("alarm"):
        number = s.alarm_number if kind == "alarm" else int(rec or 0)
        emcy, fnum, fval, injected = 0, int(number), 0, False
        text = f"alarm A{number:05d} " + ("raised" if kind == "alarm" else "gone")
    else:
        emcy = int(rec.emcy_code if rec else s.error_code)
        fnum = int(rec.fault_number) if rec else 0
        fval = int(rec.value) if rec else 0
        injected = bool(rec.injected) if rec else False
        what = f"0x{emcy:04X} F{fnum:05d} {rec.text if rec else ''}".rstrip()
        text = f"fault {what}" if kind == "fault" else f"fault acknowledged: {what}"
    return {"kind": kind, "emcy": emcy, "number": fnum, "value": fval, "injected": injected,
            "state": str(s.cia402_state), "severity": EVENT_SEVERITY[kind], "message": text}


def drive_parameters(drive: Drive) -> dict[str, float]:
    """All parameters of ``drive`` at one instant (SI units)."""
    with drive.lock:
        return {name: drive.get_parameter(name) for name in drive.parameter_names()}


SERVER_STATS_PERIOD_S = 0.5  # the server process reports its counters to serve this often
REQUEST_TIMEOUT_S = 10.0  # a write / method call forwarded to serve that got no answer in this time: BadTimeout


class OpcuaService:
    """The OPC UA server of ``axes`` (:class:`AxisSource`): serve's side (sampler and bridge threads) of the
    server process (module doc)."""

    def __init__(self, settings: OpcuaSettings, axes: list[AxisSource], gate=None):
        self.settings = settings
        self.axes = axes
        self.gate = gate
        self.bound_port: int | None = None
        self.counters = {"samples": 0, "samples_unchanged": 0, "sampler_late": 0, "writes_accepted": 0,
                         "writes_refused": 0}
        self.server_counters = {"samples_replaced": 0, "events": 0, "writes_refused": 0, "method_calls": 0,
                                "update_errors": 0}  # as last reported by the server process
        self._child = ChildProcess(f"--opcua {settings.host}:{settings.port}", "the OPC UA server", "OPC UA")
        self._stop = threading.Event()
        self._sampler: threading.Thread | None = None
        self._observers: list[tuple[Any, Callable]] = []
        self._last_alarm: dict[str, int] = {}

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self, timeout_s: float = 60.0) -> OpcuaService:
        """Start the server process, then the bridge and the sampler; returns once the server listens (OSError
        naming ``--opcua`` if it cannot)."""
        short_gil_slices()  # the bridge and the sampler never hold the drive's runtime thread for a 5 ms slice
        layout = [self._layout(ax) for ax in self.axes]
        self.bound_port = int(self._child.start("virtualaxis.services.opcua:server_child",
                                                ("init", self.settings, layout), timeout_s))
        self._child.serve(self._handle, "virtualaxis-opcua-bridge")
        for ax in self.axes:
            cb = self._observer(ax)
            ax.drive.add_observer(cb)
            self._observers.append((ax.drive, cb))
        self._sampler = threading.Thread(target=self._sample_loop, name="virtualaxis-opcua-sampler", daemon=True)
        self._sampler.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        for drive, cb in self._observers:
            drive.remove_observer(cb)
        self._observers.clear()
        if self._sampler is not None:
            self._sampler.join(timeout_s)
        self._child.stop(timeout_s)

    @property
    def server_pid(self) -> int | None:
        """The process id of the OPC UA server process (None before start)."""
        return self._child.pid

    @property
    def server_process(self) -> str:
        """not started, running, stopped, failed (why), or ended (exit code N)."""
        return self._child.status

    def stats(self) -> dict:
        out = dict(self.counters)
        srv = dict(self.server_counters)
        out["writes_refused"] += srv.pop("writes_refused", 0)
        out.update(srv)
        out.update(events_dropped=sum(a.events_dropped for a in self.axes), server_pid=self.server_pid,
                   server_process=self.server_process)
        return out

    @property
    def url(self) -> str:
        host = f"[{self.settings.host}]" if ":" in self.settings.host else self.settings.host
        return f"opc.tcp://{host}:{self.bound_port}{ENDPOINT_PATH}"

    # ------------------------------------------------------------------------------------ drive side
    def _layout(self, ax: AxisSource) -> dict:
        """What the server process needs to build the axis' nodes (plain data: it imports no drive)."""
        from virtualaxis.drive.injection import KINDS
        from virtualaxis.drive.objects import SPECS
        from virtualaxis.drive.snapshot import PARAMETERS

        s, nmt = ax.drive.state, ax.nmt()
        params = drive_parameters(ax.drive)
        limits = _eds_limits(self.settings.eds_path)
        plist = []
        for name in ax.drive.parameter_names():
            spec = PARAMETERS[name]
            dtype = SPECS[(spec.index, spec.sub)].dtype
            vt = "Double" if spec.scale != "raw" else DTYPE_VARIANT[dtype]
            plist.append((name, vt, parameter_node_value(params[name], vt), f"0x{spec.index:04X}:{spec.sub} {spec.doc}",
                          parameter_unit(name, spec.doc), _parameter_range(ax.drive, spec, dtype, limits)))
        return {"name": ax.name, "node_id": ax.node_id, "state": state_values(s, nmt), "actual": actual_values(s),
                "ranges": actual_ranges(params), "faults": fault_values(s), "parameters": plist,
                "methods": bool(self.settings.allow_fault_injection and ax.injector is not None),
                "kinds": ", ".join(KINDS)}

    def _observer(self, ax: AxisSource) -> Callable:
        def on_event(event: str, state) -> None:  # under the drive's lock: cheap and non-blocking only
            if event in ("fault", "fault_cleared"):
                self._event(ax, event, state, state.faults[0] if state.faults else None)

        return on_event

    @staticmethod
    def _event(ax: AxisSource, kind: str, state, rec) -> None:
        if len(ax.events) == ax.events.maxlen:
            ax.events_dropped += 1
        ax.events.append((kind, state, rec))

    def _sample_loop(self) -> None:
        """One compact batch of every axis' node values every SAMPLE_PERIOD_S (in the cycle's gap), parameters
        and ranges every PARAMETER_PERIOD_S; a batch equal to the last one sent is not sent."""
        period = SAMPLE_PERIOD_S
        nxt = time.perf_counter()
        next_params = 0.0
        last: list | None = None
        last_params: list | None = None
        while not self._stop.is_set() and not self._child.gone:
            now = time.perf_counter()
            if now < nxt:
                self._stop.wait(nxt - now)
                continue
            late = int((now - nxt) / period)
            if late:
                self.counters["sampler_late"] += late
                nxt += late * period
            nxt += period
            if self.gate is not None:
                self.gate.wait_next()
            batch = []
            for ax in self.axes:
                s = ax.drive.state
                if s.alarm_number != self._last_alarm.get(ax.name, 0):
                    kind = "alarm" if s.alarm_number else "alarm_cleared"
                    self._event(ax, kind, s, self._last_alarm.get(ax.name, 0) if not s.alarm_number else None)
                    self._last_alarm[ax.name] = s.alarm_number
                events = []
                while ax.events:
                    events.append(event_record(*ax.events.popleft()))
                batch.append((state_values(s, ax.nmt()), actual_values(s), fault_values(s), events))
            params = None
            if now >= next_params:
                next_params = now + PARAMETER_PERIOD_S
                params = []
                for ax in self.axes:
                    p = drive_parameters(ax.drive)
                    params.append(([p[name] for name in ax.drive.parameter_names()], actual_ranges(p)))
                if params == last_params:
                    params = None
                else:
                    last_params = params
            if batch == last and params is None:
                self.counters["samples_unchanged"] += 1
                continue
            last = batch
            if not self._child.send(("sample", batch, params)):
                return
            self.counters["samples"] += 1

    def _handle(self, msg: tuple) -> tuple | None:
        """A message of the server process: its counters, or a client's write / method call on a live drive
        (answered)."""
        kind = msg[0]
        if kind == "stats":
            self.server_counters = msg[1]
        elif kind in ("write", "call"):
            try:
                reply = self._write(*msg[2:]) if kind == "write" else self._call(*msg[2:])
            except Exception as exc:  # noqa: BLE001 - the client gets a status, serve goes on
                reply = ("BadUnexpectedError", f"{type(exc).__name__}: {exc}", None)
            return "reply", msg[1], reply
        return None

    def _write(self, axis: int, name: str, value) -> tuple[str, str, Any]:
        """A client's write of parameter ``name`` of axis number ``axis``: (status name, reason, value now)."""
        from virtualaxis.drive.core import ObjectAccessError

        drive = self.axes[axis].drive
        status, why = "Good", ""
        try:
            drive.set_parameter(name, value)
        except ObjectAccessError as exc:
            status, why = STATUS_OF_ABORT.get(exc.code, "BadUnexpectedError"), f"0x{exc.code:08X}: {exc}"
        self.counters["writes_accepted" if status == "Good" else "writes_refused"] += 1
        return status, why, drive.get_parameter(name)

    def _call(self, axis: int, action: str, kind: str | None, options: dict) -> tuple[str, str, Any]:
        """A client's InjectFault / ClearFault on axis number ``axis``: (status name, reason, active kinds)."""
        from virtualaxis.drive.injection import KINDS, InjectionRefused

        ax = self.axes[axis]
        if ax.injector is None or not self.settings.allow_fault_injection:
            return "BadNotExecutable", "fault injection is off", None
        try:
            ax.injector.command(action, kind, **options)
        except InjectionRefused as exc:
            return ("BadInvalidState" if exc.code == 0x08000022 else "BadInvalidArgument"), str(exc), None
        return "Good", "", sorted(ax.injector.active, key=lambda k: KINDS.get(k, 99))


# ============================================================================================== server process
def server_child(fd: int) -> None:
    """Entry of the OPC UA server process: the inherited socket ``fd`` joins it to serve."""
    entered = enter_child(fd)
    if entered is None:
        return
    link, (_, settings, layout) = entered
    proc = ServerProcess(link, settings, layout)
    try:
        asyncio.run(proc.main())
    except Exception as exc:  # noqa: BLE001 - reported to serve (a start-up error, or why the server ended)
        link.send(("error", f"{type(exc).__name__}: {exc}"))
        raise SystemExit(1) from None


class ServerProcess:
    """The asyncua server in its own process: node values from serve's batches, writes and method calls
    forwarded to serve (:class:`OpcuaService`), fault events emitted from serve's records."""

    def __init__(self, link: ParentLink, settings: OpcuaSettings, layout: list[dict]):
        self.link = link
        self.settings = settings
        self.layout = layout
        self.counters = {"samples_replaced": 0, "events": 0, "writes_refused": 0, "method_calls": 0,
                         "update_errors": 0}
        self._pending: tuple | None = None  # the newest batch not yet applied
        self._pending_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._stopping = False
        self._futures: dict[int, asyncio.Future] = {}
        self._ids = itertools.count(1)

    def send(self, msg: tuple) -> None:
        self.link.send(msg)

    async def request(self, *msg) -> tuple:
        """A write / method call answered by serve: (status name, reason, value)."""
        rid = next(self._ids)
        fut = self._loop.create_future()
        self._futures[rid] = fut
        self.send((msg[0], rid, *msg[1:]))
        try:
            return await asyncio.wait_for(fut, REQUEST_TIMEOUT_S)
        except asyncio.TimeoutError:
            return "BadTimeout", f"serve did not answer in {REQUEST_TIMEOUT_S:g} s", None
        finally:
            self._futures.pop(rid, None)

    async def main(self) -> None:
        space = AddressSpace(self)
        await space.build()
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self.send(("ready", space.bound_port))
        threading.Thread(target=self._read, name="virtualaxis-opcua-reader", daemon=True).start()
        next_stats = 0.0
        try:
            while not self._stopping:
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), SERVER_STATS_PERIOD_S)
                self._wake.clear()
                with self._pending_lock:
                    batch, self._pending = self._pending, None
                if batch is not None:
                    try:
                        await space.update(*batch)
                    except Exception:  # noqa: BLE001 - counted and logged once; the server goes on serving
                        self.counters["update_errors"] += 1
                        if self.counters["update_errors"] == 1:
                            import logging

                            logging.getLogger("virtualaxis").exception("OPC UA node update failed")
                if time.monotonic() >= next_stats:
                    next_stats = time.monotonic() + SERVER_STATS_PERIOD_S
                    self.send(("stats", dict(self.counters)))
        finally:
            await space.stop()
            self.send(("stats", dict(self.counters)))

    def _read(self) -> None:
        """serve's messages: batches (a batch not applied yet is replaced by the next, its events kept), replies,
        stop. EOF: serve is gone, and so is this process at once."""
        loop = self._loop
        try:
            while True:
                msg = self.link.recv()
                kind = msg[0]
                if kind == "sample":
                    self._take(msg[1], msg[2])
                    loop.call_soon_threadsafe(self._wake.set)
                elif kind == "reply":
                    loop.call_soon_threadsafe(self._resolve, msg[1], msg[2])
                elif kind == "stop":
                    break
        except (EOFError, OSError):
            os._exit(0)  # never outlive serve
        self._stopping = True
        loop.call_soon_threadsafe(self._wake.set)

    def _take(self, axes: list, params: list | None) -> None:
        with self._pending_lock:
            if self._pending is not None:
                self.counters["samples_replaced"] += 1
                old_axes, old_params = self._pending
                for old, new in zip(old_axes, axes, strict=True):
                    new[3][:0] = old[3]
                if params is None:
                    params = old_params
            self._pending = (axes, params)

    def _resolve(self, rid: int, reply: tuple) -> None:
        fut = self._futures.get(rid)
        if fut is not None and not fut.done():
            fut.set_result(reply)


class AddressSpace:
    """The nodes of the served axes in one asyncua server (built and updated in the server process)."""

    def __init__(self, proc: ServerProcess):
        self.proc = proc
        self.settings = proc.settings
        self.layout = proc.layout
        self.server = None
        self.idx = 0
        self.bound_port: int | None = None
        self.nodes: dict[str, dict[str, Any]] = {}  # axis -> var name -> node id
        self.values: dict[Any, Any] = {}  # node id -> value last written
        self.writers: dict[Any, tuple[int, str, str]] = {}  # parameter node id -> (axis number, name, vtype)
        self.own: set = set()  # node ids of our namespace
        self.events: dict[str, Any] = {}  # axis -> EventGenerators
        self.ranges: dict[Any, tuple[float, float]] = {}  # EURange node id -> (low, high) last written
        self.last_result: dict[str, Any] = {}  # axis -> LastWriteResult node id

    # ---------------------------------------------------------------- build
    async def build(self) -> None:
        from asyncua import Server, ua
        from asyncua.server.address_space import AttributeService

        st = self.settings
        server = Server(user_manager=_Users(st.users))
        await server.init()
        server.set_endpoint(st.url)
        server.set_server_name("virtualaxis")
        await server.set_application_uri(APPLICATION_URI)
        if st.cert_file:
            await server.load_certificate(st.cert_file)
            await server.load_private_key(st.key_file)
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        server.set_identity_tokens([ua.UserNameIdentityToken] if st.users else [ua.AnonymousIdentityToken])
        self.idx = await server.register_namespace(NAMESPACE_URI)
        self.server = server
        iserver = server.iserver
        space = self

        class Attributes(AttributeService):  # client writes: parameters through the drive, the rest refused
            async def write(self, params, user=None):
                from asyncua.crypto.permission_rules import User, UserRole

                user = user or User(role=UserRole.Admin)
                if user.role == UserRole.Admin:  # the server's own session (node values, set-up)
                    return await super().write(params, user)
                out = []
                for wv in params.NodesToWrite:
                    if wv.NodeId in space.own:
                        out.append(await space.client_write(wv))
                    else:
                        out.extend(await super().write(ua.WriteParameters(NodesToWrite=[wv]), user))
                return out

        iserver.attribute_service = Attributes(iserver.aspace)
        self.etype = await server.create_custom_event_type(
            self.idx, "DriveFaultEventType", ua.ObjectIds.BaseEventType,
            [(name, getattr(ua.VariantType, vt)) for name, vt in EVENT_FIELDS])
        root = await server.nodes.objects.add_folder(self._nid("VirtualAxis"), ua.QualifiedName("VirtualAxis",
                                                                                              self.idx))
        for i, ax in enumerate(self.layout):
            await self._build_axis(root, i, ax)
        await server.start()
        self.bound_port = server.bserver.port if server.bserver is not None else st.port

    def _nid(self, text: str):
        from asyncua import ua

        return ua.NodeId(text, self.idx)

    async def _var(self, parent, path: str, name: str, value, vtype: str, description: str, *,
                   analog: bool = False, writable: bool = False):
        from asyncua import ua

        array = vtype.endswith("[]")
        vt = getattr(ua.VariantType, vtype.rstrip("[]"))
        nid = self._nid(f"{path}.{name}")
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = nid
        item.BrowseName = ua.QualifiedName(name, self.idx)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.AnalogItemType if analog else ua.ObjectIds.BaseDataVariableType)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(description)
        attrs.DataType = ua.NodeId(vt.value)
        attrs.Value = ua.Variant(value, vt)
        attrs.ValueRank = ua.ValueRank.OneDimension if array else ua.ValueRank.Scalar
        attrs.ArrayDimensions = [0] if array else None
        access = ua.AccessLevel.CurrentRead.mask | (ua.AccessLevel.CurrentWrite.mask if writable else 0)
        attrs.AccessLevel = attrs.UserAccessLevel = access
        attrs.MinimumSamplingInterval = SAMPLE_PERIOD_S * 1e3
        item.NodeAttributes = attrs
        res = await parent.session.add_nodes([item])
        res[0].StatusCode.check()
        self.own.add(nid)
        self.values[nid] = value
        return self.server.get_node(nid)

    async def _analog(self, parent, path: str, name: str, value, vtype: str, description: str, unit: str | None,
                      rng: tuple[float, float], *, writable: bool = False):
        from asyncua import ua

        node = await self._var(parent, path, name, value, vtype, description, analog=True, writable=writable)
        lo, hi = rng
        r = await node.add_property(self._nid(f"{path}.{name}.EURange"), ua.QualifiedName("EURange", 0),
                                    ua.Range(Low=float(lo), High=float(hi)), datatype=ua.ObjectIds.Range)
        self.own.add(r.nodeid)
        self.ranges[r.nodeid] = (lo, hi)
        if unit is not None:
            code, display, desc = UNITS[unit]
            eu = ua.EUInformation(NamespaceUri=UNECE_NAMESPACE, UnitId=unece_unit_id(code),
                                  DisplayName=ua.LocalizedText(display), Description=ua.LocalizedText(desc))
            e = await node.add_property(self._nid(f"{path}.{name}.EngineeringUnits"),
                                        ua.QualifiedName("EngineeringUnits", 0), eu,
                                        datatype=ua.ObjectIds.EUInformation)
            self.own.add(e.nodeid)
        return node


    async def _build_axis(self, root, axis: int, ax: dict) -> None:
        from asyncua import ua

        idx, name_, base = self.idx, ax["name"], f"VirtualAxis.{ax['name']}"
        obj = await root.add_object(self._nid(base), ua.QualifiedName(name_, idx))
        self.own.add(obj.nodeid)
        p = await obj.add_property(self._nid(f"{base}.NodeId"), ua.QualifiedName("NodeId", idx), ax["node_id"],
                                   ua.VariantType.Byte)
        self.own.add(p.nodeid)
        nodes = self.nodes[name_] = {}
        folder = await obj.add_object(self._nid(f"{base}.State"), ua.QualifiedName("State", idx))
        for (name, vt, desc), value in zip(STATE_VARS, ax["state"], strict=True):
            node = await self._var(folder, f"{base}.State", name, value, vt, desc)
            nodes[name] = node.nodeid
        folder = await obj.add_object(self._nid(f"{base}.ActualValues"), ua.QualifiedName("ActualValues", idx))
        for (name, unit, _attr, desc), value, rng in zip(ACTUAL_VARS, ax["actual"], ax["ranges"], strict=True):
            node = await self._analog(folder, f"{base}.ActualValues", name, value, "Double", desc, unit, rng)
            nodes[name] = node.nodeid
        folder = await obj.add_object(self._nid(f"{base}.Faults"), ua.QualifiedName("Faults", idx))
        for (name, vt, desc), value in zip(FAULT_VARS, ax["faults"], strict=True):
            node = await self._var(folder, f"{base}.Faults", name, value, vt, desc)
            nodes[name] = node.nodeid
        folder = await obj.add_object(self._nid(f"{base}.Parameters"), ua.QualifiedName("Parameters", idx))
        for name, vt, value, desc, unit, rng in ax["parameters"]:
            node = await self._analog(folder, f"{base}.Parameters", name, value, vt, desc, unit, rng,
                                      writable=self.settings.writable)
            nodes[f"param:{name}"] = node.nodeid
            self.writers[node.nodeid] = (axis, name, vt)
        node = await self._var(folder, f"{base}.Parameters", "LastWriteResult", "", "String",
                               "the last parameter write of a client: accepted, or refused with the reason")
        self.last_result[name_] = node.nodeid
        if ax["methods"]:
            await self._methods(obj, base, axis, ax["kinds"])
        # the events go to subscribers of the axis object and of the Server object (source: the axis)
        gens = [await self.server.get_event_generator(self.etype, obj.nodeid),
                await self.server.get_event_generator(self.etype, ua.ObjectIds.Server)]
        gens[1].event.SourceNode, gens[1].event.SourceName = obj.nodeid, name_
        self.events[name_] = gens

    async def _methods(self, obj, base: str, axis: int, kinds: str) -> None:
        from asyncua import ua

        def arg(name: str, vt, desc: str) -> ua.Argument:
            return ua.Argument(Name=name, DataType=ua.NodeId(vt.value), ValueRank=ua.ValueRank.Scalar,
                               Description=ua.LocalizedText(desc))

        folder = await obj.add_object(self._nid(f"{base}.Methods"), ua.QualifiedName("Methods", self.idx))
        self.own.add(folder.nodeid)
        active = ua.Argument(Name="Active", DataType=ua.NodeId(ua.ObjectIds.String),
                             ValueRank=ua.ValueRank.OneDimension, ArrayDimensions=[0],
                             Description=ua.LocalizedText("the injected kinds now active"))
        m = await folder.add_method(
            self._nid(f"{base}.Methods.InjectFault"), ua.QualifiedName("InjectFault", self.idx),
            self._method(axis, "inject"),
            [arg("Kind", ua.VariantType.String, f"fault kind: {kinds}"),
             arg("Duty", ua.VariantType.Double, "fraction of each period the fault is present, (0, 1]; 1 permanent"),
             arg("PeriodS", ua.VariantType.Double, "period of an intermittent fault [s], 0.002..3600; "
                 "not used with Duty 1 (0 accepted)"),
             arg("Magnitude", ua.VariantType.Double, "kind-specific magnitude, 0 for the default")],
            [active])
        self.own.add(m.nodeid)
        m = await folder.add_method(
            self._nid(f"{base}.Methods.ClearFault"), ua.QualifiedName("ClearFault", self.idx),
            self._method(axis, "clear"),
            [arg("Kind", ua.VariantType.String, "fault kind to clear, '' for all (the fault itself stays until "
                                                "the master resets it)")], [active])
        self.own.add(m.nodeid)


    def _method(self, axis: int, action: str) -> Callable:
        from asyncua import ua

        want = [ua.VariantType.String] + ([ua.VariantType.Double] * 3 if action == "inject" else [])

        async def call(_parent, *args):
            self.proc.counters["method_calls"] += 1
            if len(args) < len(want):
                return ua.StatusCode(ua.StatusCodes.BadArgumentsMissing)
            if len(args) > len(want):
                return ua.StatusCode(ua.StatusCodes.BadTooManyArguments)
            if any(not isinstance(a, ua.Variant) or a.VariantType != vt for a, vt in zip(args, want, strict=True)):
                return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
            kind = args[0].Value or None
            options = {}
            if action == "inject":
                duty, period_s, magnitude = (a.Value for a in args[1:])
                options = {"duty": duty, "period_s": period_s, "magnitude": magnitude or None}
            status, _why, active = await self.proc.request("call", axis, action, kind, options)
            if status != "Good":
                return ua.StatusCode(getattr(ua.StatusCodes, status))
            return [ua.Variant(active, ua.VariantType.String)]

        return call

    # ---------------------------------------------------------------- client writes
    async def client_write(self, wv):
        """A client's write of a node of our namespace: parameters checked and applied by serve (the drive's SDO
        checks), everything else refused."""
        from asyncua import ua

        writer = self.writers.get(wv.NodeId)
        if writer is None or wv.AttributeId != ua.AttributeIds.Value or not self.settings.writable:
            self.proc.counters["writes_refused"] += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        axis, name, vt = writer
        v = wv.Value.Value if wv.Value is not None else None
        now = None
        if v is None or v.VariantType != getattr(ua.VariantType, vt) or isinstance(v.Value, (list, tuple)):
            status, why = "BadTypeMismatch", f"{name} takes a {vt}"
        elif vt == "Double" and not math.isfinite(v.Value):
            status, why = "BadOutOfRange", f"{name}: {v.Value} is not a finite number"
        else:
            status, why, now = await self.proc.request("write", axis, name, v.Value)
        ok = status == "Good"
        if now is None:  # refused here: serve never saw it
            self.proc.counters["writes_refused"] += 1
        text = f"{name} = {v.Value!r}: accepted" if ok else f"{name}: refused {status} ({why})"
        await self._write(self.last_result[self.layout[axis]["name"]], text, ua.VariantType.String)
        if now is not None:
            await self._write(wv.NodeId, parameter_node_value(now, vt), getattr(ua.VariantType, vt), force=True)
        return ua.StatusCode(getattr(ua.StatusCodes, status))

    # ---------------------------------------------------------------- updates
    async def _write(self, nid, value, vt, *, force: bool = False) -> None:
        from asyncua import ua

        if not force and self.values.get(nid) == value:
            return
        self.values[nid] = value
        await self.server.write_attribute_value(nid, ua.DataValue(ua.Variant(value, vt)))

    async def update(self, axes: list, params: list | None) -> None:
        """One batch of serve: per axis (state values, actual values, fault values, event records), and the
        parameters with the actual values' ranges (or None: unchanged)."""
        from asyncua import ua

        VT = ua.VariantType
        for ax, (state, actual, faults, events) in zip(self.layout, axes, strict=True):
            n = self.nodes[ax["name"]]
            for (name, vt, _), value in zip(STATE_VARS, state, strict=True):
                await self._write(n[name], value, getattr(VT, vt))
            for (name, *_), value in zip(ACTUAL_VARS, actual, strict=True):
                await self._write(n[name], value, VT.Double)
            for (name, vt, _), value in zip(FAULT_VARS, faults, strict=True):
                await self._write(n[name], value, getattr(VT, vt.rstrip("[]")))
            for record in events:
                await self._emit(ax["name"], record)
        if params is not None:
            await self._parameters(params)

    async def _emit(self, axis_name: str, record: dict) -> None:
        from asyncua import ua

        for gen in self.events[axis_name]:
            ev = gen.event
            ev.Axis, ev.Kind, ev.CiA402State = axis_name, record["kind"], record["state"]
            ev.EmcyCode, ev.FaultNumber = record["emcy"], record["number"]
            ev.FaultValue, ev.Injected = record["value"], record["injected"]
            ev.Severity = record["severity"]
            ev.Message = ua.LocalizedText(record["message"])
            await gen.trigger(message=ev.Message.Text)
        self.proc.counters["events"] += 1

    async def _parameters(self, params: list) -> None:
        from asyncua import ua

        for ax, (values, ranges) in zip(self.layout, params, strict=True):
            n = self.nodes[ax["name"]]
            for (name, vt, *_), value in zip(ax["parameters"], values, strict=True):
                await self._write(n[f"param:{name}"], parameter_node_value(value, vt), getattr(ua.VariantType, vt))
            for (name, *_), (lo, hi) in zip(ACTUAL_VARS, ranges, strict=True):
                rid = self._nid(f"VirtualAxis.{ax['name']}.ActualValues.{name}.EURange")
                if self.ranges.get(rid) != (lo, hi):
                    self.ranges[rid] = (lo, hi)
                    await self.server.write_attribute_value(rid, ua.DataValue(ua.Variant(
                        ua.Range(Low=float(lo), High=float(hi)), ua.VariantType.ExtensionObject)))

    async def stop(self) -> None:
        if self.server is not None:
            with contextlib.suppress(Exception):
                await self.server.stop()


def _eds_limits(eds_path: str | None) -> dict:
    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.drive.objects import eds_limits

    path = Path(eds_path) if eds_path else Path(DEFAULT_EDS)
    try:
        return eds_limits(path) if path.is_file() else {}
    except (OSError, ValueError):
        return {}


def _parameter_range(drive: Drive, spec, dtype: str, limits: dict) -> tuple[float, float]:
    """The object's data-type range narrowed by the EDS's LowLimit / HighLimit, in the parameter's SI unit."""
    from virtualaxis.drive.objects import DTYPE_RANGES

    lo, hi = DTYPE_RANGES[dtype]
    low, high = limits.get((spec.index, spec.sub), (None, None))
    lo = lo if low is None else max(lo, low)
    hi = hi if high is None else min(hi, high)
    if spec.scale == "pos":
        k = drive.scaling.metres_per_unit
    elif spec.scale == "torque_nm":
        k = float(drive.read_object(0x6076, 0)) / 1e6
    elif spec.scale == "current_a":
        k = float(drive.read_object(0x6075, 0)) / 1e6
    else:
        k = 1.0
    a, b = lo * k, hi * k
    return (min(a, b), max(a, b))


class _Users:
    """asyncua user manager: anonymous (``users`` None) or the name / password pairs of ``--opcua-users``.
    Nobody gets the administrator role: a client writes only what :meth:`AddressSpace.client_write` lets through."""

    def __init__(self, users: dict[str, str] | None):
        self.users = users

    def get_user(self, iserver, username=None, password=None, certificate=None):
        from asyncua.crypto.permission_rules import User, UserRole

        if self.users is None:
            return User(role=UserRole.User, name="anonymous")
        if username is None or username not in self.users:
            return None
        pw = password.decode() if isinstance(password, bytes) else (password or "")
        if not hmac.compare_digest(pw.encode(), self.users[username].encode()):
            return None
        return User(role=UserRole.User, name=username)


__all__ = ["NAMESPACE_URI", "AxisSource", "OpcuaService", "OpcuaSettings", "OpcuaSettingsError", "prepare"]
