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

Where the work runs: a **sampler thread** takes one ``drive.state`` per axis every :data:`SAMPLE_PERIOD_S`
(in the gap after a SYNC's PDOs when a cycle gate is given, see cycle_gate.py) and hands the snapshot to the
**server thread**, which runs the asyncio loop of the asyncua server and writes the node values (the
subscriptions sample those). A snapshot the server thread has not taken up yet is replaced by the next one
(counted: ``samples_replaced``): the drive never waits for the server. Fault events come from a drive observer
(cheap, under the drive's lock) through the sampler.

Client writes go only to ``Parameters/*`` and only with ``writable``: each is checked and applied by
``Drive.set_parameter`` (the checks of an SDO download); a refusal answers the SDO abort code's OPC UA status
(:data:`STATUS_OF_ABORT`) and leaves the value unchanged. Every other node of the namespace is read-only
(``BadNotWritable``).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from virtualaxis.services import listen
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


class OpcuaService:
    """The OPC UA server of ``axes`` (:class:`AxisSource`): a server thread and a sampler thread (module doc)."""

    def __init__(self, settings: OpcuaSettings, axes: list[AxisSource], gate=None):
        self.settings = settings
        self.axes = axes
        self.gate = gate
        self.bound_port: int | None = None
        self.counters = {"samples": 0, "samples_replaced": 0, "events": 0, "writes_accepted": 0,
                         "writes_refused": 0, "method_calls": 0, "sampler_late": 0, "update_errors": 0}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready = threading.Event()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._sampler: threading.Thread | None = None
        self._pending: list | None = None  # the newest snapshot not yet taken up by the server thread
        self._pending_lock = threading.Lock()
        self._wake: asyncio.Event | None = None
        self._observers: list[tuple[Any, Callable]] = []
        self._last_alarm: dict[str, int] = {}

    # ------------------------------------------------------------------------------------ lifecycle
    def start(self, timeout_s: float = 60.0) -> OpcuaService:
        short_gil_slices()
        self._thread = threading.Thread(target=self._run, name="virtualaxis-opcua", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s) and self._error is None:
            self._error = TimeoutError(f"the OPC UA server did not start in {timeout_s:g} s")
        if self._error is not None:
            self.stop()
            err = self._error
            raise OSError(f"--opcua {self.settings.host}:{self.settings.port}: {type(err).__name__}: {err}")
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
        if self._loop is not None and self._wake is not None:
            with contextlib.suppress(RuntimeError):  # (the loop already ended)
                self._loop.call_soon_threadsafe(self._wake.set)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def stats(self) -> dict:
        return dict(self.counters, events_dropped=sum(a.events_dropped for a in self.axes))

    @property
    def url(self) -> str:
        host = f"[{self.settings.host}]" if ":" in self.settings.host else self.settings.host
        return f"opc.tcp://{host}:{self.bound_port}{ENDPOINT_PATH}"

    # ------------------------------------------------------------------------------------ drive side
    def _observer(self, ax: AxisSource) -> Callable:
        def on_event(event: str, state) -> None:  # under the drive's lock: cheap and non-blocking only
            if event == "fault":
                self._event(ax, "fault", state, state.faults[0] if state.faults else None)
            elif event == "fault_cleared":
                self._event(ax, "fault_cleared", state, state.faults[0] if state.faults else None)

        return on_event

    @staticmethod
    def _event(ax: AxisSource, kind: str, state, rec) -> None:
        if len(ax.events) == ax.events.maxlen:
            ax.events_dropped += 1
        ax.events.append((kind, state, rec))

    def _sample_loop(self) -> None:
        period = SAMPLE_PERIOD_S
        nxt = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            if now < nxt:
                self._stop.wait(nxt - now)
                continue
            late = int((now - nxt) / period)
            if late:
                self.counters["sampler_late"] += late
                nxt += late * period
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
                    events.append(ax.events.popleft())
                batch.append((s, ax.nmt(), events))
            self._hand_over(batch)
            nxt += period

    def _hand_over(self, batch: list) -> None:
        with self._pending_lock:
            if self._pending is not None:  # not taken up yet: its events go with the newer snapshot
                self.counters["samples_replaced"] += 1
                for old, new in zip(self._pending, batch, strict=True):
                    new[2][:0] = old[2]
            self._pending = batch
        self.counters["samples"] += 1
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(wake.set)

    # ------------------------------------------------------------------------------------ server thread
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported by start() or counted; serve goes on
            if not self._ready.is_set():
                self._error = exc
                self._ready.set()
            else:
                import logging

                logging.getLogger("virtualaxis").exception("OPC UA server stopped")

    async def _main(self) -> None:
        space = AddressSpace(self)
        await space.build()
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self.bound_port = space.bound_port
        self._ready.set()
        next_params = 0.0
        try:
            while not self._stop.is_set():
                await self._wake.wait()
                self._wake.clear()
                with self._pending_lock:
                    batch, self._pending = self._pending, None
                try:
                    if batch is not None:
                        await space.update(batch)
                    if time.monotonic() >= next_params:
                        next_params = time.monotonic() + PARAMETER_PERIOD_S
                        await space.refresh_parameters()
                except Exception:  # noqa: BLE001 - counted and logged once; the server goes on serving
                    self.counters["update_errors"] += 1
                    if self.counters["update_errors"] == 1:
                        import logging

                        logging.getLogger("virtualaxis").exception("OPC UA node update failed")
        finally:
            await space.stop()


class AddressSpace:
    """The nodes of the served axes in one asyncua server (built and updated in the server thread)."""

    def __init__(self, service: OpcuaService):
        self.service = service
        self.settings = service.settings
        self.server = None
        self.idx = 0
        self.bound_port: int | None = None
        self.nodes: dict[str, dict[str, Any]] = {}  # axis -> var name -> node id
        self.values: dict[Any, Any] = {}  # node id -> value last written
        self.writers: dict[Any, tuple[AxisSource, str, str]] = {}  # parameter node id -> (axis, name, vtype)
        self.own: set = set()  # node ids of our namespace
        self.events: dict[str, Any] = {}  # axis -> EventGenerator
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
        service = self

        class Attributes(AttributeService):  # client writes: parameters through the drive, the rest refused
            async def write(self, params, user=None):
                from asyncua.crypto.permission_rules import User, UserRole

                user = user or User(role=UserRole.Admin)
                if user.role == UserRole.Admin:  # the server's own session (node values, set-up)
                    return await super().write(params, user)
                out = []
                for wv in params.NodesToWrite:
                    if wv.NodeId in service.own:
                        out.append(await service.client_write(wv))
                    else:
                        out.extend(await super().write(ua.WriteParameters(NodesToWrite=[wv]), user))
                return out

        iserver.attribute_service = Attributes(iserver.aspace)
        self.etype = await server.create_custom_event_type(
            self.idx, "DriveFaultEventType", ua.ObjectIds.BaseEventType,
            [(name, getattr(ua.VariantType, vt)) for name, vt in EVENT_FIELDS])
        root = await server.nodes.objects.add_folder(self._nid("VirtualAxis"), ua.QualifiedName("VirtualAxis",
                                                                                              self.idx))
        for ax in self.service.axes:
            await self._build_axis(root, ax)
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

    async def _build_axis(self, root, ax: AxisSource) -> None:
        from asyncua import ua

        from virtualaxis.drive.objects import SPECS
        from virtualaxis.drive.snapshot import PARAMETERS

        idx, base = self.idx, f"VirtualAxis.{ax.name}"
        obj = await root.add_object(self._nid(base), ua.QualifiedName(ax.name, idx))
        self.own.add(obj.nodeid)
        p = await obj.add_property(self._nid(f"{base}.NodeId"), ua.QualifiedName("NodeId", idx), ax.node_id,
                                   ua.VariantType.Byte)
        self.own.add(p.nodeid)
        nodes = self.nodes[ax.name] = {}
        s, nmt = ax.drive.state, ax.nmt()
        folder = await obj.add_object(self._nid(f"{base}.State"), ua.QualifiedName("State", idx))
        for name, vt, desc in STATE_VARS:
            node = await self._var(folder, f"{base}.State", name, _state_value(name, s, nmt), vt, desc)
            nodes[name] = node.nodeid
        params = self._parameters(ax)
        folder = await obj.add_object(self._nid(f"{base}.ActualValues"), ua.QualifiedName("ActualValues", idx))
        for name, unit, attr, desc in ACTUAL_VARS:
            node = await self._analog(folder, f"{base}.ActualValues", name, float(getattr(s, attr)), "Double", desc,
                                      unit, ACTUAL_RANGES[name](params))
            nodes[name] = node.nodeid
        folder = await obj.add_object(self._nid(f"{base}.Faults"), ua.QualifiedName("Faults", idx))
        for name, vt, desc in FAULT_VARS:
            node = await self._var(folder, f"{base}.Faults", name, _fault_value(name, s), vt, desc)
            nodes[name] = node.nodeid
        folder = await obj.add_object(self._nid(f"{base}.Parameters"), ua.QualifiedName("Parameters", idx))
        limits = _eds_limits(self.settings.eds_path)
        for name in ax.drive.parameter_names():
            spec = PARAMETERS[name]
            dtype = SPECS[(spec.index, spec.sub)].dtype
            vt = "Double" if spec.scale != "raw" else DTYPE_VARIANT[dtype]
            value = params[name] if vt == "Double" else int(round(params[name]))
            rng = _parameter_range(ax.drive, spec, dtype, limits)
            node = await self._analog(folder, f"{base}.Parameters", name, value, vt,
                                      f"0x{spec.index:04X}:{spec.sub} {spec.doc}", parameter_unit(name, spec.doc),
                                      rng, writable=self.settings.writable)
            nodes[f"param:{name}"] = node.nodeid
            self.writers[node.nodeid] = (ax, name, vt)
        node = await self._var(folder, f"{base}.Parameters", "LastWriteResult", "", "String",
                               "the last parameter write of a client: accepted, or refused with the reason")
        self.last_result[ax.name] = node.nodeid
        if self.settings.allow_fault_injection and ax.injector is not None:
            await self._methods(obj, base, ax)
        # the events go to subscribers of the axis object and of the Server object (source: the axis)
        gens = [await self.server.get_event_generator(self.etype, obj.nodeid),
                await self.server.get_event_generator(self.etype, ua.ObjectIds.Server)]
        gens[1].event.SourceNode, gens[1].event.SourceName = obj.nodeid, ax.name
        self.events[ax.name] = gens

    async def _methods(self, obj, base: str, ax: AxisSource) -> None:
        from asyncua import ua

        from virtualaxis.drive.injection import KINDS

        def arg(name: str, vt, desc: str) -> ua.Argument:
            return ua.Argument(Name=name, DataType=ua.NodeId(vt.value), ValueRank=ua.ValueRank.Scalar,
                               Description=ua.LocalizedText(desc))

        folder = await obj.add_object(self._nid(f"{base}.Methods"), ua.QualifiedName("Methods", self.idx))
        self.own.add(folder.nodeid)
        kinds = ", ".join(KINDS)
        active = ua.Argument(Name="Active", DataType=ua.NodeId(ua.ObjectIds.String),
                             ValueRank=ua.ValueRank.OneDimension, ArrayDimensions=[0],
                             Description=ua.LocalizedText("the injected kinds now active"))
        m = await folder.add_method(
            self._nid(f"{base}.Methods.InjectFault"), ua.QualifiedName("InjectFault", self.idx),
            self._method(ax, "inject"),
            [arg("Kind", ua.VariantType.String, f"fault kind: {kinds}"),
             arg("Duty", ua.VariantType.Double, "fraction of each period the fault is present, (0, 1]; 1 permanent"),
             arg("PeriodS", ua.VariantType.Double, "period of an intermittent fault [s], 0.002..3600"),
             arg("Magnitude", ua.VariantType.Double, "kind-specific magnitude, 0 for the default")],
            [active])
        self.own.add(m.nodeid)
        m = await folder.add_method(
            self._nid(f"{base}.Methods.ClearFault"), ua.QualifiedName("ClearFault", self.idx),
            self._method(ax, "clear"),
            [arg("Kind", ua.VariantType.String, "fault kind to clear, '' for all (the fault itself stays until "
                                                "the master resets it)")], [active])
        self.own.add(m.nodeid)

    def _method(self, ax: AxisSource, action: str) -> Callable:
        from asyncua import ua

        from virtualaxis.drive.injection import KINDS, InjectionRefused

        want = [ua.VariantType.String] + ([ua.VariantType.Double] * 3 if action == "inject" else [])

        async def call(_parent, *args):
            self.service.counters["method_calls"] += 1
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
            try:
                ax.injector.command(action, kind, **options)
            except InjectionRefused as exc:
                bad = "BadInvalidState" if exc.code == 0x08000022 else "BadInvalidArgument"
                return ua.StatusCode(getattr(ua.StatusCodes, bad))
            active = sorted(ax.injector.active, key=lambda k: KINDS.get(k, 99))
            return [ua.Variant(active, ua.VariantType.String)]

        return call

    # ---------------------------------------------------------------- client writes
    async def client_write(self, wv):
        from asyncua import ua

        from virtualaxis.drive.core import ObjectAccessError

        writer = self.writers.get(wv.NodeId)
        if writer is None or wv.AttributeId != ua.AttributeIds.Value or not self.settings.writable:
            self.service.counters["writes_refused"] += 1
            return ua.StatusCode(ua.StatusCodes.BadNotWritable)
        ax, name, vt = writer
        v = wv.Value.Value if wv.Value is not None else None
        status, why = "Good", ""
        if v is None or v.VariantType != getattr(ua.VariantType, vt) or isinstance(v.Value, (list, tuple)):
            status, why = "BadTypeMismatch", f"{name} takes a {vt}"
        elif vt == "Double" and not math.isfinite(v.Value):
            status, why = "BadOutOfRange", f"{name}: {v.Value} is not a finite number"
        else:
            try:
                ax.drive.set_parameter(name, v.Value)
            except ObjectAccessError as exc:
                status, why = STATUS_OF_ABORT.get(exc.code, "BadUnexpectedError"), f"0x{exc.code:08X}: {exc}"
        ok = status == "Good"
        self.service.counters["writes_accepted" if ok else "writes_refused"] += 1
        text = f"{name} = {v.Value!r}: accepted" if ok else f"{name}: refused {status} ({why})"
        await self._write(self.last_result[ax.name], text, ua.VariantType.String)
        await self._write(wv.NodeId, self._param_value(ax, name, vt), getattr(ua.VariantType, vt), force=True)
        return ua.StatusCode(getattr(ua.StatusCodes, status))

    @staticmethod
    def _param_value(ax: AxisSource, name: str, vt: str):
        v = ax.drive.get_parameter(name)
        return v if vt == "Double" else int(round(v))

    # ---------------------------------------------------------------- updates
    async def _write(self, nid, value, vt, *, force: bool = False) -> None:
        from asyncua import ua

        if not force and self.values.get(nid) == value:
            return
        self.values[nid] = value
        await self.server.write_attribute_value(nid, ua.DataValue(ua.Variant(value, vt)))

    async def update(self, batch: list) -> None:
        from asyncua import ua

        VT = ua.VariantType
        for ax, (s, nmt, events) in zip(self.service.axes, batch, strict=True):
            n = self.nodes[ax.name]
            for name, vt, _ in STATE_VARS:
                await self._write(n[name], _state_value(name, s, nmt), getattr(VT, vt))
            for name, _unit, attr, _ in ACTUAL_VARS:
                await self._write(n[name], float(getattr(s, attr)), VT.Double)
            for name, vt, _ in FAULT_VARS:
                await self._write(n[name], _fault_value(name, s), getattr(VT, vt.rstrip("[]")))
            for kind, es, rec in events:
                await self._emit(ax, kind, es, rec)

    async def _emit(self, ax: AxisSource, kind: str, s, rec) -> None:
        for gen in self.events[ax.name]:
            self._fill(gen.event, ax, kind, s, rec)
            await gen.trigger(message=gen.event.Message.Text)
        self.service.counters["events"] += 1

    @staticmethod
    def _fill(ev, ax: AxisSource, kind: str, s, rec) -> None:
        from asyncua import ua

        if kind.startswith("alarm"):
            number = s.alarm_number if kind == "alarm" else int(rec or 0)
            ev.EmcyCode, ev.FaultNumber, ev.FaultValue, ev.Injected = 0, number, 0, False
            text = f"alarm A{number:05d} " + ("raised" if kind == "alarm" else "gone")
        else:
            ev.EmcyCode = rec.emcy_code if rec else s.error_code
            ev.FaultNumber = rec.fault_number if rec else 0
            ev.FaultValue = int(rec.value) if rec else 0
            ev.Injected = bool(rec.injected) if rec else False
            what = f"0x{ev.EmcyCode:04X} F{ev.FaultNumber:05d} {rec.text if rec else ''}".rstrip()
            text = f"fault {what}" if kind == "fault" else f"fault acknowledged: {what}"
        ev.Axis, ev.Kind, ev.CiA402State = ax.name, kind, s.cia402_state
        ev.Severity = EVENT_SEVERITY[kind]
        ev.Message = ua.LocalizedText(text)

    async def refresh_parameters(self) -> None:
        from asyncua import ua

        for ax in self.service.axes:
            params = self._parameters(ax)
            n = self.nodes[ax.name]
            for name, value in params.items():
                nid = n.get(f"param:{name}")
                if nid is None:
                    continue
                vt = self.writers[nid][2]
                await self._write(nid, value if vt == "Double" else int(round(value)), getattr(ua.VariantType, vt))
            for name, *_ in ACTUAL_VARS:
                rid = self._nid(f"VirtualAxis.{ax.name}.ActualValues.{name}.EURange")
                lo, hi = ACTUAL_RANGES[name](params)
                if self.ranges.get(rid) != (lo, hi):
                    self.ranges[rid] = (lo, hi)
                    await self.server.write_attribute_value(rid, ua.DataValue(ua.Variant(
                        ua.Range(Low=float(lo), High=float(hi)), ua.VariantType.ExtensionObject)))

    @staticmethod
    def _parameters(ax: AxisSource) -> dict[str, float]:
        d = ax.drive
        with d.lock:  # one instant
            return {name: d.get_parameter(name) for name in d.parameter_names()}

    async def stop(self) -> None:
        if self.server is not None:
            with contextlib.suppress(Exception):
                await self.server.stop()


def _state_value(name: str, s, nmt: str):
    return {
        "CiA402State": s.cia402_state, "Statusword": s.statusword, "Controlword": s.controlword,
        "ModeOfOperation": s.mode, "ModeName": s.mode_name, "NmtState": nmt, "Homed": bool(s.homed),
        "TargetReached": bool(s.target_reached), "Warning": bool(s.warning), "DriveTime": float(s.time_s),
    }[name]


def _fault_value(name: str, s):
    if name == "FaultActive":
        return bool(s.fault_active)
    if name == "ErrorCode":
        return int(s.error_code)
    if name == "ActiveFault":
        active = [f for f in s.faults if not f.acknowledged] if s.fault_active else []
        return f"0x{active[0].emcy_code:04X} F{active[0].fault_number:05d} {active[0].text}" if active else ""
    if name == "AlarmNumber":
        return int(s.alarm_number)
    if name == "FaultBuffer":
        return [fault_line(f) for f in s.faults]
    return [int(f.emcy_code) for f in s.faults]  # FaultCodes


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
