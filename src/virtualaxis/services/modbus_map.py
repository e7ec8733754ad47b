"""The Modbus TCP register map of one axis: data in one place (:data:`REGISTERS`).

Everything about a register lives in its :class:`Register` row: number (Modicon 4xxxx, PDU address =
number - 40001), width, type, access, scaling, the value it shows and the drive object a write goes to.
The server (:mod:`virtualaxis.services.modbus`) and the document ``docs/modbus-map.md``
(:func:`render_markdown`, ``python3 -m virtualaxis.services.modbus_map --write docs/modbus-map.md``) are both
generated from this table.

Conventions (SINAMICS Modbus TCP style):

- 32-bit values are two consecutive registers, **high word first** (big-endian word order, "ABCD"); each
  16-bit register is big-endian on the wire as Modbus defines.
- Signed values are two's complement. A value that does not fit its register is shown **saturated**
  (as SINAMICS does), never wrapped.
- Writes go through the drive's own object write (:meth:`Drive.write_object`): the same validation as an SDO
  download, applied live to the running drive.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from virtualaxis import __version__
from virtualaxis.drive.injection import (
    ABORT_DEVICE_STATE,
    KIND_NAMES,
    OBJ_CLEAR,
    OBJ_DUTY,
    OBJ_INJECT,
    OBJ_PERIOD,
    InjectionRefused,
    channel_options,
    check_channel_value,
)

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive
    from virtualaxis.drive.injection import FaultInjector

_LAST_KIND = max(KIND_NAMES)  # the highest fault-injection kind number (the map's texts name the range)

# ---------------------------------------------------------------------------------------------- errors
# reason codes of the last-error register 40499 (and the exception each one answers with)
REASON_NONE = 0
REASON_WRITES_DISABLED = 1  # 04: the server runs without --modbus-writable
REASON_READ_ONLY = 2  # 04: the register is read-only
REASON_DRIVE_STATE = 3  # 04: the drive refuses the value in its present state (SDO abort 0x08000022)
REASON_DRIVE_VALUE = 4  # 03: the drive refuses the value (SDO abort 0x0609003x / 0x06090030)
REASON_REGISTER_RANGE = 5  # 03: the value does not fit the register's type or scaling
REASON_PARTIAL_PAIR = 6  # 03: a write covers only one half of a 32-bit register pair
REASON_UNKNOWN_REGISTER = 7  # 02: unknown register or a range that crosses a hole
REASON_BAD_COUNT = 8  # 03: register count out of range for the function
REASON_UNSUPPORTED_FUNCTION = 9  # 01: function code not supported
REASON_BAD_LENGTH = 10  # 03: the request's PDU is too short or too long for its function (or its byte count)

REASONS: dict[int, tuple[int, str]] = {
    REASON_NONE: (0, "no error since start"),
    REASON_WRITES_DISABLED: (4, "writes are disabled (server started without --modbus-writable)"),
    REASON_READ_ONLY: (4, "register is read-only"),
    REASON_DRIVE_STATE: (4, "the drive refuses the write in its present state (SDO abort 0x08000022)"),
    REASON_DRIVE_VALUE: (3, "the drive refuses the value (SDO abort 0x06090030/31/32: invalid, too high, too low)"),
    REASON_REGISTER_RANGE: (3, "value out of the register's range"),
    REASON_PARTIAL_PAIR: (3, "a write must cover both registers of a 32-bit value"),
    REASON_UNKNOWN_REGISTER: (2, "unknown register, or the range crosses a hole in the map"),
    REASON_BAD_COUNT: (3, "register count out of range (FC03/04: 1..125, FC16: 1..123, FC23: 1..125 / 1..121)"),
    REASON_UNSUPPORTED_FUNCTION: (1, "function code not supported (only 03, 04, 06, 16, 23)"),
    REASON_BAD_LENGTH: (3, "request too short or too long for its function code, or a byte count (FC16, FC23) "
                           "other than 2 x the register count or other than the data bytes sent"),
}


class RegisterError(Exception):
    """A refused register access; ``reason`` is a REASON_* code, ``exception_code`` the Modbus exception."""

    def __init__(self, reason: int, message: str, *, address: int = 0, abort_code: int = 0):
        super().__init__(message)
        self.reason = reason
        self.exception_code = REASONS[reason][0]
        self.address = address
        self.abort_code = abort_code


# ---------------------------------------------------------------------------------------------- types
DTYPES: dict[str, tuple[int, int, int]] = {
    # name: (words, min, max)
    "u16": (1, 0, 0xFFFF),
    "i16": (1, -0x8000, 0x7FFF),
    "bits": (1, 0, 0xFFFF),
    "u32": (2, 0, 0xFFFFFFFF),
    "i32": (2, -0x80000000, 0x7FFFFFFF),
}

CIA402_STATE_CODES = {
    "NOT READY TO SWITCH ON": 0,
    "SWITCH ON DISABLED": 1,
    "READY TO SWITCH ON": 2,
    "SWITCHED ON": 3,
    "OPERATION ENABLED": 4,
    "QUICK STOP ACTIVE": 5,
    "FAULT REACTION ACTIVE": 6,
    "FAULT": 7,
}

STW1_TO_CONTROLWORD_MASK = 0x008F  # bits 0-3 (ON/OFF1, OFF2, OFF3, enable operation) and 7 (acknowledge)
STW1_CONTROL_BY_PLC = 0x0400  # bit 10: the PLC (this Modbus writer) takes control; 0: the write's bits are ignored


def saturate(value: float, dtype: str) -> int:
    """Round to an integer and saturate to ``dtype``'s range (NaN reads as 0)."""
    _, lo, hi = DTYPES[dtype]
    if value != value:  # NaN
        return 0
    if value >= hi:
        return hi
    if value <= lo:
        return lo
    return int(round(value))


def to_words(value: int, dtype: str) -> list[int]:
    """An integer already within ``dtype``'s range as its 16-bit register words (high word first)."""
    words = DTYPES[dtype][0]
    if words == 1:
        return [value & 0xFFFF]
    v = value & 0xFFFFFFFF
    return [v >> 16, v & 0xFFFF]


def from_words(words: list[int], dtype: str) -> int:
    """Register words (high word first) as the signed/unsigned integer of ``dtype``."""
    v = 0
    for w in words:
        v = (v << 16) | (w & 0xFFFF)
    if dtype in ("i16", "i32"):
        bits = 16 * len(words)
        if v >= 1 << (bits - 1):
            v -= 1 << bits
    return v


# ---------------------------------------------------------------------------------------------- per-axis view
class AxisLink:
    """What the Modbus map needs of one served axis: the drive, its unit id (= CANopen node id) and the
    service-side settings (reference speed p2000) and last-error record."""

    def __init__(self, drive: Drive, unit_id: int, *, reference_speed_rpm: float | None = None,
                 injector: FaultInjector | None = None):
        self.drive = drive
        self.unit_id = unit_id
        self.injector = injector  # the axis' FaultInjector (None: the fault-injection registers refuse)
        # options of the next injection (40600..40604), kept by the Modbus server like 0x5FF2..0x5FF4 on CAN
        self.fault_duty_permille = 0
        self.fault_period_ms = 1000
        self.fault_magnitude = 0
        self.fault_last_injected = 0  # kind number last injected / cleared through Modbus (40605 / 40606)
        self.fault_last_cleared = 0
        cfg = drive.cfg
        self.lead_m = cfg.mechanics.lead_m if cfg.mechanics.lead_m > 0 else 0.01  # drive's virtual revolution
        self.force_actuator = cfg.actuator.kind == "force"
        rated = cfg.motor.rated_speed_rpm
        self.reference_speed_rpm = int(round(reference_speed_rpm or rated or 3000.0))
        self.last_error_reason = REASON_NONE
        self.last_error_address = 0
        self.last_error_abort_code = 0
        self.requests = 0
        self.exceptions = 0

    def record_error(self, exc: RegisterError) -> None:
        self.last_error_reason = exc.reason
        self.last_error_address = exc.address
        self.last_error_abort_code = exc.abort_code
        self.exceptions += 1

    @property
    def injection_allowed(self) -> bool:
        return self.injector is not None and bool(self.injector.allowed)

    def active_fault_bits(self) -> int:
        """Bit (kind number - 1) set for each injected kind (as 0x5FF5)."""
        return 0 if self.injector is None else self.injector.active_bits

    def rpm_per_m_s(self) -> float:
        """Motor (or virtual) revolutions per minute per m/s of table speed."""
        return 60.0 / self.lead_m


class View:
    """The values one request reads: the drive state taken once (one lock), parameters read on demand.

    The state is cached per view without a lock of its own: ``functools.cached_property`` of Python < 3.12
    holds one lock per property for every instance, so a view built under the drive's lock (the register
    image) and one whose state waits for that lock (a request) would wait for each other for ever."""

    def __init__(self, link: AxisLink):
        self.link = link
        self.drive = link.drive
        self._state = None

    @property
    def s(self):
        state = self._state
        if state is None:
            state = self._state = self.drive.state
        return state

    def obj(self, index: int, sub: int = 0) -> float:
        return float(self.drive.read_object(index, sub))

    def param(self, name: str) -> float:
        return self.drive.get_parameter(name)

    def norm_speed(self, v_m_s: float) -> float:
        """Table speed as SINAMICS normalised speed: 0x4000 = 100 % of the reference speed (40324)."""
        return v_m_s * self.link.rpm_per_m_s() / self.link.reference_speed_rpm * 0x4000


def zsw1(v: View) -> int:
    """SINAMICS ZSW1 from the CiA 402 statusword (bit meanings in the map's notes)."""
    s = v.s
    sw = s.statusword
    word = sw & 0x02FF  # bits 0-7 and 9 are the same bits as in 0x6041
    window_m_s = v.obj(0x606D) * v.drive.scaling.metres_per_unit
    if abs(s.velocity_actual_m_s - s.velocity_demand_m_s) <= window_m_s:
        word |= 1 << 8
    if sw & 0x0400:
        word |= 1 << 10
    if not sw & 0x0800:
        word |= 1 << 11
    if s.cia402_state == "OPERATION ENABLED":
        word |= 1 << 12
    if s.alarm_number != 7910:
        word |= 1 << 13
    if s.velocity_actual_m_s >= 0:
        word |= 1 << 14
    word |= 1 << 15
    return word


def _power_kw(v: View) -> float:
    s = v.s
    if v.link.force_actuator:
        return s.torque_nm * s.velocity_actual_m_s / 1000.0
    omega = s.velocity_actual_m_s / v.link.lead_m * 2.0 * math.pi
    return s.torque_nm * omega / 1000.0


def _fault_field(i: int, what: str) -> Callable[[View], float]:
    def read(v: View) -> float:
        faults = v.s.faults
        if i >= len(faults):
            return 0
        f = faults[i]
        return {"number": f.fault_number, "code": f.emcy_code, "value": f.value}[what]

    return read


def _version_number() -> int:
    parts = [int(p) for p in (__version__.split(".") + ["0", "0"])[:3] if p.isdigit()]
    while len(parts) < 3:
        parts.append(0)
    return parts[0] * 10000 + parts[1] * 100 + parts[2]


# ---------------------------------------------------------------------------------------------- writes
@dataclass(frozen=True)
class ObjectWrite:
    """A register write mapped onto a drive object: ``obj_value = register_value * factor`` (then rounded to an
    integer unless the object is a float), with ``factor`` possibly depending on the axis."""

    index: int
    sub: int
    factor: float | Callable[[AxisLink], float] = 1.0
    integer: bool = True
    unscaled: int | None = None  # a register value written as it is (e.g. 0xFFFFFFFF "off")

    def object_value(self, link: AxisLink, value: int) -> float | int:
        if value == self.unscaled:
            return value
        f = self.factor(link) if callable(self.factor) else self.factor
        x = value * f
        return int(round(x)) if self.integer else float(x)


def _pos_factor(scale_m: float) -> Callable[[AxisLink], float]:
    """Register in ``scale_m`` metres -> drive position units."""
    return lambda link: scale_m / link.drive.scaling.metres_per_unit


def _speed_setpoint_factor(link: AxisLink) -> float:
    """Normalised speed (0x4000 = reference speed) -> 0x60FF target velocity [position units/s]."""
    m_s_per_unit = link.reference_speed_rpm / 0x4000 / link.rpm_per_m_s()
    return m_s_per_unit / link.drive.scaling.metres_per_unit


def _current_factor(link: AxisLink) -> float:
    """A x 10 -> 0x6073 per mille of the rated current 0x6075 [mA]."""
    rated_a = float(link.drive.read_object(0x6075, 0)) / 1000.0
    return 0.1 / rated_a * 1000.0 if rated_a > 0 else 0.0


# ---------------------------------------------------------------------------------------------- the map
@dataclass(frozen=True)
class Register:
    """One register (or 32-bit pair) of the map."""

    number: int  # Modicon number 4xxxx of the first word (PDU address = number - 40001)
    name: str
    dtype: str  # u16 | i16 | bits | u32 | i32
    scaling: str  # what one count means
    meaning: str
    read: Callable[[View], float]
    write: ObjectWrite | Callable[[AxisLink, int], None] | None = None
    source: str = ""  # drive object / Siemens counterpart
    value_range: tuple[int, int] | None = None  # the values a write may carry where narrower than the type's

    @property
    def words(self) -> int:
        return DTYPES[self.dtype][0]

    @property
    def address(self) -> int:
        return self.number - 40001

    @property
    def writable(self) -> bool:
        return self.write is not None


def _alarm_code(v: View) -> int:
    """The EMCY code of the active alarm (40408): the warning's own code, 0x4310 for the motor-temperature
    alarm A07910; 0 without an alarm."""
    number = v.s.alarm_number
    if not number:
        return 0
    for code, alarm in v.drive.warnings.items():
        if alarm == number:
            return code
    return 0x4310 if number == 7910 else 0


def _fe_tolerance_um(v: View) -> float:
    """0x6065 in um, 0xFFFFFFFF (monitoring off) as it is."""
    raw = v.obj(0x6065)
    return raw if raw == 0xFFFFFFFF else raw * v.drive.scaling.metres_per_unit * 1e6


def _write_stw1(link: AxisLink, value: int) -> None:
    """STW1 with bit 10 "control by PLC" set: bits 0-3 and 7 go to the CiA 402 controlword 0x6040. Bit 7
    acknowledges faults on every write that has it set (a rising edge is made if the controlword already had
    bit 7). Bit 10 = 0: the writer does not take control (SINAMICS r0054.10); the write changes nothing (a
    CANopen master that drives the axis keeps it)."""
    if not value & STW1_CONTROL_BY_PLC:
        return
    drive = link.drive
    cw = value & STW1_TO_CONTROLWORD_MASK
    if cw & 0x80 and drive.state.controlword & 0x80:
        drive.write_object(0x6040, 0, cw & ~0x80)
    drive.write_object(0x6040, 0, cw)


def _check_stw1(link: AxisLink, value: int) -> None:
    if value & STW1_CONTROL_BY_PLC:
        link.drive.check_object_write(0x6040, 0, value & STW1_TO_CONTROLWORD_MASK)


def _write_reference_speed(link: AxisLink, value: int) -> None:
    link.reference_speed_rpm = value


def _check_reference_speed(link: AxisLink, value: int) -> None:
    if value < 1:
        raise RegisterError(REASON_REGISTER_RANGE, f"reference speed must be >= 1 rpm (got {value})")


# ---- fault injection (40600 ...): the CANopen channel 0x5FF0..0x5FF6 of drive/injection.py on Modbus, with its
# value checks (check_channel_value) and option conversion (channel_options)
def _injection_refused(link: AxisLink, message: str, code: int) -> RegisterError:
    reason = REASON_DRIVE_STATE if code == ABORT_DEVICE_STATE else REASON_DRIVE_VALUE
    return RegisterError(reason, message, abort_code=code)


def _check_injection(link: AxisLink, index: int | None = None, value: int = 0) -> None:
    """Allowed on this axis, and (``index`` of the CANopen channel object) the value the channel accepts."""
    if link.injector is None:
        raise _injection_refused(link, "fault injection is not available on this axis", ABORT_DEVICE_STATE)
    if not link.injector.allowed:
        raise _injection_refused(link, "fault injection is off (serve with --allow-fault-injection)",
                                 ABORT_DEVICE_STATE)
    if index is not None:
        try:
            check_channel_value(index, value)
        except InjectionRefused as exc:
            raise _injection_refused(link, str(exc), exc.code) from None


def _check_fault_duty(link: AxisLink, value: int) -> None:
    _check_injection(link, OBJ_DUTY, value)


def _write_fault_duty(link: AxisLink, value: int) -> None:
    link.fault_duty_permille = value


def _check_fault_period(link: AxisLink, value: int) -> None:
    _check_injection(link, OBJ_PERIOD, value)


def _write_fault_period(link: AxisLink, value: int) -> None:
    link.fault_period_ms = value


def _check_fault_magnitude(link: AxisLink, value: int) -> None:
    _check_injection(link)


def _write_fault_magnitude(link: AxisLink, value: int) -> None:
    link.fault_magnitude = value


def _check_fault_inject(link: AxisLink, value: int) -> None:
    _check_injection(link, OBJ_INJECT, value)


def _run_injection(link: AxisLink, action: str, kind: int | None, **options) -> None:
    try:
        link.injector.command(action, kind, **options)
    except InjectionRefused as exc:
        raise _injection_refused(link, str(exc), exc.code) from None


def _write_fault_inject(link: AxisLink, value: int) -> None:
    _run_injection(link, "inject", value,
                   **channel_options(link.fault_duty_permille, link.fault_period_ms, link.fault_magnitude))
    link.fault_last_injected = value


def _check_fault_clear(link: AxisLink, value: int) -> None:
    _check_injection(link, OBJ_CLEAR, value)


def _write_fault_clear(link: AxisLink, value: int) -> None:
    _run_injection(link, "clear", None if value in (0, 0xFF) else value)
    link.fault_last_cleared = value


# custom writes that are not a plain object write: (check, apply)
CUSTOM_CHECKS: dict[Callable, Callable[[AxisLink, int], None]] = {
    _write_stw1: _check_stw1,
    _write_reference_speed: _check_reference_speed,
    _write_fault_duty: _check_fault_duty,
    _write_fault_period: _check_fault_period,
    _write_fault_magnitude: _check_fault_magnitude,
    _write_fault_inject: _check_fault_inject,
    _write_fault_clear: _check_fault_clear,
}

P = _pos_factor


def _r(number, name, dtype, scaling, meaning, read, write=None, source="", value_range=None):
    return Register(number, name, dtype, scaling, meaning, read, write, source, value_range)


REGISTERS: tuple[Register, ...] = (
    # ---- process data: control (40100 ...)
    _r(40100, "STW1", "bits", "bits", "control word 1: with bit 10 (control by PLC) set, bits 0-3 and 7 -> "
       "CiA 402 controlword 0x6040 (0 ON/OFF1, 1 OFF2, 2 OFF3, 3 enable operation, 7 acknowledge fault); bit 10 "
       "= 0: the write is ignored; reads 0x6040",
       lambda v: v.s.controlword, _write_stw1, "r0054 / 0x6040"),
    _r(40101, "NSOLL_A", "i16", "0x4000 = 100 % of the reference speed (40324)",
       "speed set-point: reads the drive's speed demand; writes target velocity 0x60FF (PV / CSV modes)",
       lambda v: v.norm_speed(v.s.velocity_demand_m_s), ObjectWrite(0x60FF, 0, _speed_setpoint_factor),
       "p1070 / 0x60FF"),
    _r(40102, "MODE", "i16", "1", "modes of operation 0x6060 (1 PP, 3 PV, 4 PT, 6 HM, 8 CSP, 9 CSV, 10 CST)",
       lambda v: v.obj(0x6060), ObjectWrite(0x6060, 0), "0x6060"),
    # ---- process data: status (40110 ...)
    _r(40110, "ZSW1", "bits", "bits", "status word 1 (bits in the notes below)", zsw1, None, "r0052"),
    _r(40111, "NIST_A", "i16", "0x4000 = 100 % of the reference speed (40324)", "actual speed",
       lambda v: v.norm_speed(v.s.velocity_actual_m_s), None, "r0063"),
    _r(40112, "POS_ACT", "i32", "1 um", "position actual (drive coordinate, homed)",
       lambda v: v.s.position_actual_m * 1e6, None, "0x6064"),
    _r(40114, "FOLLOW_ERR", "i32", "1 um", "following error (demand - actual; 0 outside position control)",
       lambda v: v.s.following_error_m * 1e6, None, "r2563 / 0x60F4"),
    _r(40116, "POS_DEMAND", "i32", "1 um", "position demand", lambda v: v.s.position_demand_m * 1e6, None,
       "0x6062"),
    _r(40118, "CIA402_STATE", "u16", "code", "CiA 402 state: 0 not ready to switch on, 1 switch on disabled, "
       "2 ready to switch on, 3 switched on, 4 operation enabled, 5 quick stop active, 6 fault reaction "
       "active, 7 fault", lambda v: CIA402_STATE_CODES.get(v.s.cia402_state, 0), None, "0x6041"),
    _r(40119, "MODE_DISPLAY", "i16", "1", "modes of operation display 0x6061", lambda v: v.s.mode, None, "0x6061"),
    _r(40120, "STATUSWORD", "bits", "bits", "CiA 402 statusword 0x6041", lambda v: v.s.statusword, None,
       "0x6041"),
    _r(40121, "ERROR_CODE", "u16", "EMCY code", "error code 0x603F of the latest fault (0: none)",
       lambda v: v.s.error_code, None, "0x603F"),
    # ---- drive identification and reference values
    _r(40300, "POWER_UNIT", "u16", "code", "power unit code number (0: the simulated power unit has no catalogue "
       "code)", lambda v: 0, None, "r0200"),
    _r(40301, "FIRMWARE", "u16", "major x 10000 + minor x 100 + patch", "firmware (package) version",
       lambda v: _version_number(), None, "r0018"),
    _r(40321, "CURRENT_LIMIT", "u16", "0.1 A", "current limit", lambda v: v.param("current_limit_a") * 10,
       ObjectWrite(0x6073, 0, _current_factor), "p0640 / 0x6073"),
    _r(40324, "REF_SPEED", "u16", "1 rpm", "reference speed (100 % of 40101 / 40111); kept by the Modbus "
       "server, default the motor's rated speed; 1..65535", lambda v: v.link.reference_speed_rpm,
       _write_reference_speed, "p2000", (1, 65535)),
    # ---- monitoring block (40340 ... 40383, contiguous)
    _r(40340, "SPEED_SET_RPM", "i16", "1 rpm", "speed set-point (motor)",
       lambda v: v.s.velocity_demand_m_s * v.link.rpm_per_m_s(), None, "r0020"),
    _r(40341, "SPEED_ACT_RPM", "i16", "1 rpm", "actual speed (motor)",
       lambda v: v.s.velocity_actual_m_s * v.link.rpm_per_m_s(), None, "r0022"),
    _r(40342, "MAX_SPEED_RPM", "u16", "1 rpm", "max motor speed 0x6080", lambda v: v.obj(0x6080),
       ObjectWrite(0x6080, 0), "p1082 / 0x6080"),
    _r(40343, "FEED_ACT", "i16", "0.01 m/min", "actual table feed",
       lambda v: v.s.velocity_actual_m_s * 60.0 * 100.0, None, "r0063"),
    _r(40344, "DC_LINK", "u16", "1 V", "DC-link voltage", lambda v: v.s.dc_link_v, None, "r0026 / 0x6079"),
    _r(40345, "CURRENT_ACT", "i16", "0.01 A", "actual (q) current", lambda v: v.s.current_a * 100, None,
       "r0027"),
    _r(40346, "TORQUE_ACT", "i16", "0.01 N m (N for a linear motor)", "actual torque",
       lambda v: v.s.torque_nm * 100, None, "r0031"),
    _r(40347, "POWER_ACT", "i16", "0.01 kW", "active (mechanical) power", lambda v: _power_kw(v) * 100, None,
       "r0032"),
    _r(40348, "TABLE_POS", "i32", "1 um", "table position (linear scale, plant coordinate)",
       lambda v: v.s.table_position_m * 1e6, None, "r0482"),
    _r(40350, "VELOCITY_ACT", "i32", "1 um/s", "actual table velocity", lambda v: v.s.velocity_actual_m_s * 1e6,
       None, "0x606C"),
    _r(40352, "VELOCITY_DEMAND", "i32", "1 um/s", "table velocity demand",
       lambda v: v.s.velocity_demand_m_s * 1e6, None, "0x606B"),
    _r(40354, "TORQUE_PERMILLE", "i16", "0.1 % of rated torque", "actual torque 0x6077", lambda v: v.obj(0x6077),
       None, "0x6077"),
    _r(40355, "CURRENT_PERMILLE", "i16", "0.1 % of rated current", "actual current 0x6078",
       lambda v: v.obj(0x6078), None, "0x6078"),
    _r(40356, "DIGITAL_INPUTS", "bits", "bits", "digital inputs 0x60FD (0 neg. limit, 1 pos. limit, 2 home)",
       lambda v: v.s.digital_inputs & 0xFFFF, None, "0x60FD"),  # (bits 16 / 17, the probe inputs: not here)
    _r(40357, "HOMED", "u16", "0/1", "homing attained since power on", lambda v: 1 if v.s.homed else 0, None, ""),
    _r(40358, "TEMP_ALARM", "i16", "1 C", "motor temperature alarm threshold (A07910)",
       lambda v: v.param("motor_temperature_alarm_c"), ObjectWrite(0x200A, 0, 1.0, integer=False),
       "p0604 / 0x200A"),
    _r(40359, "TEMP_FAULT", "i16", "1 C", "motor temperature fault threshold (F07011)",
       lambda v: v.param("motor_temperature_fault_c"), ObjectWrite(0x200B, 0, 1.0, integer=False),
       "p0605 / 0x200B"),
    _r(40360, "MOTOR_TEMP", "i16", "0.1 C", "motor temperature", lambda v: v.s.motor_temperature_c * 10, None,
       "r0035 / 0x2020"),
    _r(40361, "KV", "u16", "0.01 (1000/min) = 0.01 (m/min)/mm", "position-loop gain Kv",
       lambda v: v.param("kv_1000_per_min") * 100, ObjectWrite(0x2000, 0, 0.01, integer=False),
       "MD32200 / 0x2000"),
    _r(40362, "SPEED_PRECONTROL", "u16", "0.1 %", "speed precontrol (feed-forward) factor",
       lambda v: v.param("velocity_ff_factor") * 1000, ObjectWrite(0x2001, 0, 0.001, integer=False),
       "p2534 / MD32610 / 0x2001"),
    _r(40363, "SPEED_KP", "u16", "0.001 N m s/rad", "speed controller P gain",
       lambda v: v.param("speed_kp") * 1000, ObjectWrite(0x2003, 0, 0.001, integer=False), "p1460 / 0x2003"),
    _r(40364, "SPEED_TN", "u16", "0.1 ms", "speed controller integral time (0: P only)",
       lambda v: v.param("speed_tn_ms") * 10, ObjectWrite(0x2004, 0, 0.1, integer=False), "p1462 / 0x2004"),
    _r(40365, "FE_TOLERANCE", "u32", "1 um", "following error tolerance (0xFFFFFFFF: off)",
       _fe_tolerance_um, ObjectWrite(0x6065, 0, P(1e-6), unscaled=0xFFFFFFFF),
       "p2546 / 0x6065"),
    _r(40367, "FE_TIME", "u16", "1 ms", "following error time", lambda v: v.obj(0x6066), ObjectWrite(0x6066, 0),
       "0x6066"),
    _r(40368, "STANDSTILL_WINDOW", "u32", "1 um", "standstill window",
       lambda v: v.param("standstill_window_m") * 1e6, ObjectWrite(0x2006, 0, P(1e-6)), "p2542 / 0x2006"),
    _r(40370, "STANDSTILL_TIME", "u16", "1 ms", "standstill time", lambda v: v.obj(0x2007),
       ObjectWrite(0x2007, 0), "p2543 / 0x2007"),
    _r(40371, "POSITIONING_WINDOW", "u32", "1 um", "positioning window",
       lambda v: v.param("positioning_window_m") * 1e6, ObjectWrite(0x6067, 0, P(1e-6)), "p2544 / 0x6067"),
    _r(40373, "POSITIONING_TIME", "u16", "1 ms", "positioning time", lambda v: v.obj(0x6068),
       ObjectWrite(0x6068, 0), "p2545 / 0x6068"),
    _r(40374, "FF_MODE", "u16", "code", "feed-forward mode: 0 off, 1 speed, 2 speed + torque",
       lambda v: v.obj(0x2002), ObjectWrite(0x2002, 0), "MD32620 / 0x2002"),
    _r(40375, "EXT_FORCE", "i16", "1 N", "external (cutting / disturbance) force on the table",
       lambda v: v.param("external_force_n"), ObjectWrite(0x2011, 0, 1.0, integer=False), "0x2011"),
    _r(40376, "CYCLES", "u32", "1", "drive cycles run", lambda v: v.s.cycles, None, "0x2110:5"),
    _r(40378, "OVERRUNS", "u32", "1", "drive cycles that started late (real-time pacing)",
       lambda v: v.drive.counters["overruns"], None, "0x2110:2"),
    _r(40380, "FAULTS_RAISED", "u32", "1", "faults raised since power on",
       lambda v: v.drive.counters["faults_raised"], None, ""),
    _r(40382, "DRIVE_TIME", "u32", "1 ms", "drive (plant) time", lambda v: v.s.time_s * 1000, None, ""),
    # ---- fault and alarm buffer (40400 ...)
    *(
        _r(40400 + i, f"FAULT_NUMBER_{i}", "u16", "F number", f"fault number [{i}] (0 newest; 0: empty)",
           _fault_field(i, "number"), None, f"r0947[{i}]")
        for i in range(8)
    ),
    _r(40408, "ALARM_NUMBER", "u16", "A number", "active alarm number (e.g. 7910 motor temperature; 0: none)",
       lambda v: v.s.alarm_number, None, "r2122 / 0x2031"),
    _r(40409, "ALARM_CODE", "u16", "EMCY code", "CiA 402 code of the active alarm of 40408 (0: none)", _alarm_code,
       None, "r2124 / 0x2031"),
    *(
        _r(40410 + i, f"FAULT_CODE_{i}", "u16", "EMCY code", f"fault code [{i}] (CiA 402 EMCY code)",
           _fault_field(i, "code"), None, f"r0945[{i}]")
        for i in range(8)
    ),
    _r(40419, "FAULT_COUNT", "u16", "1", "entries in the fault buffer (0..8)", lambda v: len(v.s.faults), None, ""),
    *(
        _r(40420 + 2 * i, f"FAULT_VALUE_{i}", "i32", "1", f"fault value [{i}]", _fault_field(i, "value"), None,
           f"r0949[{i}]")
        for i in range(8)
    ),
    # ---- last parameter access error (40496 ... 40499)
    _r(40496, "LAST_ERROR_ADDRESS", "u16", "PDU address", "PDU address of the last refused access",
       lambda v: v.link.last_error_address, None, ""),
    _r(40497, "LAST_ERROR_ABORT", "u32", "SDO abort code", "SDO abort code of the last value the drive refused "
       "(0: the refusal came from the Modbus layer)", lambda v: v.link.last_error_abort_code, None, ""),
    _r(40499, "LAST_ERROR", "u16", "reason code", "reason of the last refused access (table below)",
       lambda v: v.link.last_error_reason, None, "40499 (S120)"),
    # ---- fault injection (40600 ... 40609; writes refused unless serve --allow-fault-injection)
    _r(40600, "FI_DUTY", "u16", "1 per mille", "duty cycle of the next injection (0 or 1000: permanent; else "
       "intermittent, active for duty x period of every period)", lambda v: v.link.fault_duty_permille,
       _write_fault_duty, "0x5FF2", (0, 1000)),
    _r(40601, "FI_PERIOD", "u32", "1 ms", "period of the intermittent variant (2..3600000)",
       lambda v: v.link.fault_period_ms, _write_fault_period, "0x5FF3", (2, 3_600_000)),
    _r(40603, "FI_MAGNITUDE", "i32", "kind-specific", "magnitude of the next injection (brake force [N], limit "
       "switch side, heating [K/s], bus-off time [ms]; 0: the kind's default)", lambda v: v.link.fault_magnitude,
       _write_fault_magnitude, "0x5FF4"),
    _r(40605, "FI_INJECT", "u16", "kind number", f"write a kind number 1..{_LAST_KIND} to inject it with 40600-40604 "
       "(docs/fault-injection.md); reads the kind last injected through Modbus", lambda v: v.link.fault_last_injected,
       _write_fault_inject, "0x5FF0"),
    _r(40606, "FI_CLEAR", "u16", "kind number", "write a kind number to clear it (0 or 255: all); reads the "
       "value last written", lambda v: v.link.fault_last_cleared, _write_fault_clear, "0x5FF1"),
    _r(40607, "FI_ACTIVE", "u32", "bit (kind number - 1)",
       f"injected kinds (bit 0 {KIND_NAMES[1]} ... bit {_LAST_KIND - 1} {KIND_NAMES[_LAST_KIND]})",
       lambda v: v.link.active_fault_bits(), None, "0x5FF5"),
    _r(40609, "FI_ALLOWED", "u16", "0/1", "1 when the axis accepts fault injection (serve "
       "--allow-fault-injection)", lambda v: 1 if v.link.injection_allowed else 0, None, "0x5FF6"),
)

BY_ADDRESS: dict[int, tuple[Register, int]] = {}  # PDU address -> (register, word index within it)
for _reg in REGISTERS:
    for _w in range(_reg.words):
        if _reg.address + _w in BY_ADDRESS:
            raise RuntimeError(f"modbus map: register {_reg.number + _w} defined twice")
        BY_ADDRESS[_reg.address + _w] = (_reg, _w)
BY_NAME: dict[str, Register] = {r.name: r for r in REGISTERS}


# ---------------------------------------------------------------------------------------------- access
def read_block(link: AxisLink, address: int, count: int, view: View | None = None) -> list[int]:
    """``count`` register words from PDU ``address`` (raises :class:`RegisterError` for a hole). ``view``: a
    snapshot to read from (requests answered together share one; default a fresh one)."""
    for a in range(address, address + count):
        if a not in BY_ADDRESS:
            raise RegisterError(
                REASON_UNKNOWN_REGISTER, f"register {a + 40001} (address {a}) is not in the map", address=a
            )
    view = view if view is not None else View(link)
    out: list[int] = []
    a = address
    end = address + count
    while a < end:
        reg, w = BY_ADDRESS[a]
        words = to_words(saturate(reg.read(view), reg.dtype), reg.dtype)
        take = words[w : w + (end - a)]
        out.extend(take)
        a += len(take)
    return out


def check_mapped(address: int, count: int) -> None:
    """Every register of ``count`` from ``address`` is in the map (exception 02 otherwise: the address check comes
    before any other check of a write, as the Modbus application protocol's processing diagrams have it)."""
    for a in range(address, address + count):
        if a not in BY_ADDRESS:
            raise RegisterError(
                REASON_UNKNOWN_REGISTER, f"register {a + 40001} (address {a}) is not in the map", address=a
            )


def decode_writes(link: AxisLink, address: int, values: list[int]) -> list[tuple[Register, int]]:
    """The (register, value) writes that ``values`` at ``address`` make; checks the addresses, the pairing
    of 32-bit values, writability and the register ranges (not yet the drive's validation)."""
    check_mapped(address, len(values))
    out = []
    i = 0
    while i < len(values):
        a = address + i
        reg, w = BY_ADDRESS[a]
        if not reg.writable:
            raise RegisterError(REASON_READ_ONLY, f"register {reg.number} {reg.name} is read-only", address=a)
        if w != 0 or i + reg.words > len(values):
            raise RegisterError(
                REASON_PARTIAL_PAIR,
                f"register {reg.number} {reg.name} is a 32-bit value: write registers {reg.number} and "
                f"{reg.number + 1} in one request",
                address=a,
            )
        out.append((reg, from_words(values[i : i + reg.words], reg.dtype)))
        i += reg.words
    return out


def check_write(link: AxisLink, reg: Register, value: int) -> None:
    """Validate one write as the drive would (SDO-identical), without applying it."""
    from virtualaxis.drive.core import ObjectAccessError

    try:
        if isinstance(reg.write, ObjectWrite):
            link.drive.check_object_write(reg.write.index, reg.write.sub, reg.write.object_value(link, value))
        else:
            CUSTOM_CHECKS[reg.write](link, value)
    except ObjectAccessError as exc:
        raise _drive_refusal(reg, exc) from None
    except RegisterError as exc:
        raise _at(reg, exc) from None


def apply_write(link: AxisLink, reg: Register, value: int) -> None:
    """Apply one (checked) write to the drive."""
    from virtualaxis.drive.core import ObjectAccessError

    try:
        if isinstance(reg.write, ObjectWrite):
            link.drive.write_object(reg.write.index, reg.write.sub, reg.write.object_value(link, value))
        else:
            reg.write(link, value)
    except ObjectAccessError as exc:
        raise _drive_refusal(reg, exc) from None
    except RegisterError as exc:
        raise _at(reg, exc) from None


def _at(reg: Register, exc: RegisterError) -> RegisterError:
    """A custom check's refusal at ``reg`` (its address and name in the message)."""
    if not exc.address:
        exc.address = reg.address
    return exc


def _drive_refusal(reg: Register, exc) -> RegisterError:
    reason = REASON_DRIVE_STATE if exc.code in (0x08000022, 0x06010002, 0x08000020, 0x08000021) else (
        REASON_DRIVE_VALUE
    )
    return RegisterError(
        reason, f"register {reg.number} {reg.name}: {exc}", address=reg.address, abort_code=int(exc.code)
    )


def write_block(link: AxisLink, address: int, values: list[int]) -> None:
    """Write registers: every value is checked first (map, pairing, drive validation); only then are they
    applied, in address order. A refused request changes nothing."""
    writes = decode_writes(link, address, values)
    for reg, value in writes:
        check_write(link, reg, value)
    for reg, value in writes:
        apply_write(link, reg, value)


# ---------------------------------------------------------------------------------------------- document
ZSW1_BITS = (
    (0, "ready to switch on (0x6041 bit 0)"),
    (1, "ready / switched on (0x6041 bit 1)"),
    (2, "operation enabled (0x6041 bit 2)"),
    (3, "fault present (0x6041 bit 3)"),
    (4, "OFF2 inactive / voltage enabled (0x6041 bit 4)"),
    (5, "OFF3 inactive / no quick stop (0x6041 bit 5)"),
    (6, "switching on inhibited (0x6041 bit 6)"),
    (7, "alarm present (0x6041 bit 7)"),
    (8, "speed set-point / actual deviation within tolerance (|actual - demand| <= velocity window 0x606D)"),
    (9, "control requested (0x6041 bit 9, remote)"),
    (10, "target reached (0x6041 bit 10)"),
    (11, "no current / torque / position limit active (0x6041 bit 11 inverted)"),
    (12, "holding brake open (operation enabled)"),
    (13, "no motor over-temperature alarm (A07910)"),
    (14, "motor rotates forwards (actual velocity >= 0)"),
    (15, "no power unit thermal overload alarm (always 1)"),
)


def _ranges() -> list[tuple[int, int]]:
    """Contiguous register ranges (Modicon numbers, inclusive)."""
    addrs = sorted(BY_ADDRESS)
    out = []
    start = prev = addrs[0]
    for a in addrs[1:]:
        if a != prev + 1:
            out.append((start + 40001, prev + 40001))
            start = a
        prev = a
    out.append((start + 40001, prev + 40001))
    return out


def render_markdown() -> str:
    """``docs/modbus-map.md``: generated from :data:`REGISTERS` (do not edit the file by hand)."""
    lines = [
        "# Modbus TCP register map",
        "",
        "<!-- GENERATED from src/virtualaxis/services/modbus_map.py by "
        "`python3 -m virtualaxis.services.modbus_map --write docs/modbus-map.md`; "
        "tests/test_services_modbus.py fails when this file and the map differ. -->",
        "",
        "`virtualaxis serve ... --modbus [HOST:PORT]` (default `127.0.0.1:5020`) serves this map for every axis; "
        "the **unit id is the axis' CANopen node id** (one server for a multi-axis `serve`). Writes need "
        "`--modbus-writable`.",
        "",
        "The same map for import into SCADA / HMI tools, generated from the same data: "
        "[modbus-map.csv](modbus-map.csv) (one row per register or 32-bit pair: register, PDU address, words, name, "
        "type, signed, min, max, access, scaling, meaning, source) and [modbus-map.json](modbus-map.json) (the "
        "same rows under `registers`, with the conventions and the contiguous ranges).",
        "",
        "## Conventions",
        "",
        "- Register numbers are Modicon 4xxxx numbers as in the SINAMICS manuals: register 4xxxx is PDU "
        "address xxxx - 1 (40110 ZSW1 = address 109).",
        "- Function codes: 03 read holding registers, 04 read input registers (the same map), 06 write single "
        "register, 16 write multiple registers, 23 read/write multiple registers (write first, then read).",
        "- 32-bit values (`u32`, `i32`) are two registers, **high word first** (big-endian word order); each "
        "register is big-endian on the wire. Signed values are two's complement.",
        "- Values that do not fit their register are shown **saturated** at the type's limit (as SINAMICS does), "
        "never wrapped. Reading one half of a 32-bit value is allowed; a write must cover both halves.",
        "- Writes are checked exactly like an SDO download of the drive object named in the *source* column "
        "and apply live to the running drive. A multi-register write is checked completely before anything is "
        "applied: a refused request changes nothing.",
        "- STW1 (40100): as on a SINAMICS drive, bit 10 (control by PLC) says whether the writer takes control. "
        "Bit 10 = 1: bits 0-3 and 7 are written to the CiA 402 controlword 0x6040; the other bits are ignored. "
        "Bit 10 = 0: the write is answered normally and changes nothing (a CANopen master that drives the axis "
        "keeps it; a Modbus writer cannot switch the axis off by writing 0). Every write with bits 10 and 7 set "
        "acknowledges faults (rising edge; a fault whose cause persists stays, as on the drive). `0x047E` = "
        "ready (shutdown), `0x047F` = run (switch on + enable operation), `0x0400` = off (OFF1).",
        "- The speed normalisation of 40101 / 40111 uses the reference speed 40324 (default: the motor's rated "
        "speed); for a linear motor one revolution is 10 mm of travel.",
        "- Fault injection 40600-40609 is the CANopen channel 0x5FF0..0x5FF6 (docs/fault-injection.md) on Modbus: "
        "set the options 40600-40604 (kept by the Modbus server per unit, like 40324), then write the kind number "
        f"(1 {KIND_NAMES[1]} ... {_LAST_KIND} {KIND_NAMES[_LAST_KIND]}) to 40605; one FC16 request covering "
        "40600-40605 does both (a request is "
        "applied in address order). 40606 clears a kind (0 or 255: all); 40607-40608 has bit n-1 set while kind n "
        "is injected. Every write of the block needs `--modbus-writable` **and** `serve --allow-fault-injection` "
        "(else exception 04, 40499 = 3, 40497-40498 = 0x08000022); an unknown kind number or an option out of "
        "range answers exception 03 (40499 = 4, 0x06090030).",
        "",
        "## Exceptions",
        "",
        "| exception | when | 40499 reason |",
        "|---|---|---|",
        "| 01 illegal function | a function code other than 03, 04, 06, 16, 23 (0x00 and 0x80..0xFF too) | 9 |",
        "| 02 illegal data address | a register that is not in the map, or a range that crosses a hole | 7 |",
        "| 03 illegal data value | count out of range (FC03/04 1..125, FC16 1..123, FC23 read 1..125 / write "
        "1..121), a value outside the register's range, a write covering half of a 32-bit value, a value the "
        "drive refuses (SDO abort 0x06090030/31/32; an unknown fault kind number), a request too short or too "
        "long for its function code or whose byte count (FC16, FC23) does not fit its count or its data | "
        "8, 5, 6, 4, 10 |",
        "| 04 server device failure | a write while writes are disabled, a write to a read-only register, a "
        "write the drive refuses in its present state (SDO abort 0x08000022; fault injection not allowed) | 1, 2, 3 |",
        "",
        "An unknown unit id is answered with exception 0B (gateway target device failed to respond). Unit ids "
        "0 and 255 (\"this device\" in Modbus TCP gateways and SCADA drivers) address the axis when `serve` "
        "serves a single axis: reads and writes, each answered (Modbus TCP has no broadcast, so a write to unit 0 "
        "is applied and answered like any other). With several axes they name no axis: exception 0B.",
        "",
        "Last-error registers (per unit): 40499 reason code, 40496 PDU address of the refused register, "
        "40497-40498 the drive's SDO abort code (0 when the Modbus layer refused). They keep the last error.",
        "",
        "| 40499 | exception | reason |",
        "|---|---|---|",
    ]
    for code, (exc, text) in REASONS.items():
        lines.append(f"| {code} | {exc:02d} | {text} |")
    lines += [
        "",
        "## Contiguous ranges",
        "",
        "A read must stay inside one range (else exception 02):",
        "",
    ]
    lines += [f"- {a}-{b} ({b - a + 1} registers)" if b > a else f"- {a} (1 register)" for a, b in _ranges()]
    lines += [
        "",
        "## Registers",
        "",
        "| register | address | name | type | access | scaling | meaning | source |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in REGISTERS:
        num = f"{r.number}" if r.words == 1 else f"{r.number}-{r.number + 1}"
        addr = f"{r.address}" if r.words == 1 else f"{r.address}-{r.address + 1}"
        acc = "RW" if r.writable else "R"
        lines.append(f"| {num} | {addr} | {r.name} | {r.dtype} | {acc} | {r.scaling} | {r.meaning} | {r.source} |")
    lines += ["", "## ZSW1 bits (40110)", "", "| bit | meaning |", "|---|---|"]
    lines += [f"| {b} | {t} |" for b, t in ZSW1_BITS]
    lines.append("")
    return "\n".join(lines)


MACHINE_READABLE_FIELDS = ("register", "address", "words", "name", "type", "signed", "min", "max", "access",
                           "scaling", "meaning", "source")


def register_rows() -> list[dict]:
    """The register map as plain rows (one per register or 32-bit pair), the content of ``docs/modbus-map.csv``
    and ``docs/modbus-map.json``: ``register`` Modicon number of the first word, ``address`` its PDU address
    (0-based), ``words`` 1 or 2 (high word first), ``min`` / ``max`` the values the register holds (its type's
    range, or the narrower range a write is checked against), ``access`` R or RW (RW: written with
    ``--modbus-writable``)."""
    rows = []
    for r in REGISTERS:
        _, lo, hi = DTYPES[r.dtype]
        if r.value_range is not None:
            lo, hi = r.value_range
        rows.append({"register": r.number, "address": r.address, "words": r.words, "name": r.name,
                     "type": r.dtype, "signed": r.dtype.startswith("i"), "min": lo, "max": hi,
                     "access": "RW" if r.writable else "R", "scaling": r.scaling, "meaning": r.meaning,
                     "source": r.source})
    return rows


def render_csv() -> str:
    """``docs/modbus-map.csv``: :func:`register_rows` as CSV (RFC 4180, header row, comma, UTF-8)."""
    import csv
    import io

    out = io.StringIO()
    w = csv.DictWriter(out, fieldnames=MACHINE_READABLE_FIELDS, lineterminator="\n")
    w.writeheader()
    for row in register_rows():
        w.writerow(row | {"signed": "true" if row["signed"] else "false"})
    return out.getvalue()


def render_json() -> str:
    """``docs/modbus-map.json``: the conventions, the contiguous ranges and :func:`register_rows`."""
    import json

    doc = {
        "schema": 1,
        "register_numbering": "Modicon 4xxxx: PDU address = register - 40001",
        "word_order": "high word first (big-endian); each register big-endian on the wire",
        "signed": "two's complement",
        "out_of_range_values": "saturated at the type's limit",
        "function_codes": [3, 4, 6, 16, 23],
        "contiguous_ranges": [[a, b] for a, b in _ranges()],
        "registers": register_rows(),
    }
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"


RENDERERS: dict[str, Callable[[], str]] = {".md": render_markdown, ".csv": render_csv, ".json": render_json}


def main(argv: list[str] | None = None) -> int:
    import argparse
    from pathlib import Path

    p = argparse.ArgumentParser(description="print or write docs/modbus-map.md (.csv, .json) from the register map")
    p.add_argument("--write", metavar="FILE", help="write the document to FILE instead of printing it; the format "
                   "follows the suffix: .md, .csv or .json")
    p.add_argument("--format", choices=("md", "csv", "json"), default=None,
                   help="the format printed (default md, or the suffix of --write)")
    args = p.parse_args(argv)
    suffix = f".{args.format}" if args.format else (Path(args.write).suffix.lower() if args.write else ".md")
    if suffix not in RENDERERS:
        print(f"error: --write {args.write}: unknown suffix {suffix!r} (expected .md, .csv or .json)",
              file=sys.stderr)
        return 2
    text = RENDERERS[suffix]()
    if args.write:
        Path(args.write).write_text(text)
    else:
        print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
