"""The CiA 402 (0x6xxx) and manufacturer (0x2xxx) objects the drive application implements.

:data:`OBJECTS` is the drive's own list: index, sub-index, name, data type, access and a fallback default.
When the drive is served through a CANopen slave, the values the EDS declares win (the EDS is loaded into
the slave's object dictionary); :func:`missing_from_eds` lists the objects of this table that an EDS lacks.
Objects derived from the axis configuration (scaling, motor data, loop gains) are written at boot and on
NMT reset node, see :meth:`virtualaxis.drive.Drive.derived_objects`.

Units (with the default feed constant of the drive, 1 position unit = 1 um at the table):
position [pos unit], velocity [pos unit/s], acceleration [pos unit/s^2], jerk [pos unit/s^3],
torque / current [per mille of rated 0x6076 / 0x6075], times [ms], DC link [mV].
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

from virtualaxis.drive.opmodes import SUPPORTED_MODE_BITS

DTYPE_RANGES: dict[str, tuple[int, int]] = {
    "u8": (0, 0xFF),
    "i8": (-0x80, 0x7F),
    "u16": (0, 0xFFFF),
    "i16": (-0x8000, 0x7FFF),
    "u32": (0, 0xFFFFFFFF),
    "i32": (-0x80000000, 0x7FFFFFFF),
    "f32": (-3.4e38, 3.4e38),
}


@dataclass(frozen=True)
class ObjectSpec:
    """One object (or sub-object) of the drive application."""

    index: int
    sub: int
    name: str
    dtype: str  # key of DTYPE_RANGES
    access: str  # "rw", "ro", "wo"
    default: int | float

    @property
    def key(self) -> tuple[int, int]:
        return (self.index, self.sub)


def _o(index: int, sub: int, name: str, dtype: str, access: str, default: int) -> ObjectSpec:
    return ObjectSpec(index, sub, name, dtype, access, default)


# Supported modes 0x6502: PP 0x1, PV 0x4, PT 0x8, HM 0x20, IP 0x40, CSP 0x80, CSV 0x100, CST 0x200
SUPPORTED_MODES_BITS = 0x1 | 0x4 | 0x8 | 0x20 | 0x40 | 0x80 | 0x100 | 0x200
MODE_BITS = SUPPORTED_MODE_BITS  # 0x6502: the modes of drive.opmodes

OBJECTS: tuple[ObjectSpec, ...] = (
    # manufacturer objects (Siemens-style loop parameters, monitoring, faults, diagnostics)
    # 0x2000..0x2004: the default axis' values (configs/seed000-hust.toml, the seed axis as published: speed
    # feed-forward off); at boot the served axis config writes its own (configs/tuned-drive.toml: 0x2001 = 1.0,
    # 0x2002 = 1)
    _o(0x2000, 0, "position loop gain Kv [1000/min]", "f32", "rw", 5.538),
    _o(0x2001, 0, "velocity feed-forward factor [1]", "f32", "rw", 0.0),
    _o(0x2002, 0, "feed-forward mode (0 off, 1 speed, 2 speed + torque)", "u8", "rw", 0),
    _o(0x2003, 0, "speed controller P gain [N m s/rad]", "f32", "rw", 6.9),
    _o(0x2004, 0, "speed controller integral time Tn [ms]", "f32", "rw", 40.0),
    _o(0x2005, 0, "following error tolerance (= 0x6065)", "u32", "rw", 1000),
    _o(0x2006, 0, "standstill window", "u32", "rw", 200),
    _o(0x2007, 0, "standstill time [ms]", "u16", "rw", 200),
    _o(0x2008, 0, "positioning window (= 0x6067)", "u32", "rw", 40),
    _o(0x2009, 0, "positioning time [ms] (= 0x6068)", "u16", "rw", 100),
    _o(0x200A, 0, "motor temperature alarm threshold [C]", "f32", "rw", 130.0),
    _o(0x200B, 0, "motor temperature fault threshold [C]", "f32", "rw", 145.0),
    _o(0x2010, 0, "fault injection command (EMCY code; 0 clears injected faults)", "u16", "rw", 0),
    _o(0x2011, 0, "external force on the table [N]", "f32", "rw", 0.0),
    _o(0x2012, 0, "software limit reaction (0 clamp + SW bit 11, 1 fault EMCY 0x8612)", "u8", "rw", 0),
    _o(0x2013, 0, "limit switch reaction (0 warning A07491/2 + stop, 1 fault F07491/2 0xFF10/0xFF11)", "u8", "rw",
       1),
    _o(0x2014, 1, "touch probe input 1: switching position (machine coordinate; 0x7FFFFFFF never)", "i32", "rw",
       0x7FFFFFFF),
    _o(0x2014, 2, "touch probe input 2: switching position (machine coordinate; 0x7FFFFFFF never)", "i32", "rw",
       0x7FFFFFFF),
    _o(0x2014, 3, "touch probe inputs forced active (bit 0 input 1, bit 1 input 2)", "u8", "rw", 0),
    _o(0x2020, 0, "motor temperature [C]", "f32", "ro", 20.0),
    _o(0x2040, 0, "brake opening delay [ms]", "u16", "rw", 0),
    _o(0x2041, 0, "brake closing delay [ms]", "u16", "rw", 0),
    _o(0x2042, 0, "STO input (1 = safe torque off demanded)", "u8", "rw", 0),
    *(_o(0x2030, i, f"fault number {i - 1} (r0947)", "u16", "ro", 0) for i in range(1, 9)),
    _o(0x2031, 0, "alarm number", "u16", "ro", 0),
    *(_o(0x2032, i, f"fault code {i - 1} (EMCY, r0945)", "u16", "ro", 0) for i in range(1, 9)),
    *(_o(0x2033, i, f"fault value {i - 1} (r0949)", "i32", "ro", 0) for i in range(1, 9)),
    _o(0x2110, 1, "illegal controlword transitions", "u32", "ro", 0),
    _o(0x2110, 2, "drive cycle overruns", "u32", "ro", 0),
    _o(0x2110, 3, "targets clamped to software limits", "u32", "ro", 0),
    _o(0x2110, 4, "faults raised", "u32", "ro", 0),
    _o(0x2110, 5, "drive cycles run", "u32", "ro", 0),
    _o(0x2110, 6, "exceptions caught in the drive cycle", "u32", "ro", 0),
    _o(
        0x6007,
        0,
        "abort connection option code (0 none, 1 fault, 2 disable voltage, 3 quick stop)",
        "i16",
        "rw",
        1,
    ),
    # CiA 402
    _o(0x603F, 0, "error code", "u16", "ro", 0),
    _o(0x6040, 0, "controlword", "u16", "rw", 0),
    _o(0x6041, 0, "statusword", "u16", "ro", 0x0250),
    _o(0x605A, 0, "quick stop option code", "i16", "rw", 2),
    _o(0x605B, 0, "shutdown option code", "i16", "rw", 0),
    _o(0x605C, 0, "disable operation option code", "i16", "rw", 1),
    _o(0x605D, 0, "halt option code", "i16", "rw", 1),
    _o(0x605E, 0, "fault reaction option code", "i16", "rw", 2),
    _o(0x6060, 0, "modes of operation", "i8", "rw", 0),
    _o(0x6061, 0, "modes of operation display", "i8", "ro", 0),
    _o(0x6062, 0, "position demand value", "i32", "ro", 0),
    _o(0x6063, 0, "position actual internal value [inc]", "i32", "ro", 0),
    _o(0x6064, 0, "position actual value", "i32", "ro", 0),
    _o(0x6065, 0, "following error window", "u32", "rw", 2000),
    _o(0x6066, 0, "following error time out [ms]", "u16", "rw", 10),
    _o(0x6067, 0, "position window", "u32", "rw", 10),
    _o(0x6068, 0, "position window time [ms]", "u16", "rw", 10),
    _o(0x606B, 0, "velocity demand value", "i32", "ro", 0),
    _o(0x606C, 0, "velocity actual value", "i32", "ro", 0),
    _o(0x606D, 0, "velocity window", "u16", "rw", 1000),
    _o(0x606E, 0, "velocity window time [ms]", "u16", "rw", 10),
    _o(0x606F, 0, "velocity threshold", "u16", "rw", 100),
    _o(0x6070, 0, "velocity threshold time [ms]", "u16", "rw", 10),
    _o(0x6071, 0, "target torque [per mille]", "i16", "rw", 0),
    _o(0x6072, 0, "max torque [per mille]", "u16", "rw", 3000),
    _o(0x6073, 0, "max current [per mille]", "u16", "rw", 3000),
    _o(0x6074, 0, "torque demand [per mille]", "i16", "ro", 0),
    _o(0x6075, 0, "motor rated current [mA]", "u32", "rw", 12500),
    _o(0x6076, 0, "motor rated torque [mN m]", "u32", "rw", 18000),
    _o(0x6077, 0, "torque actual value [per mille]", "i16", "ro", 0),
    _o(0x6078, 0, "current actual value [per mille]", "i16", "ro", 0),
    _o(0x6079, 0, "DC link circuit voltage [mV]", "u32", "ro", 0),
    _o(0x607A, 0, "target position", "i32", "rw", 0),
    _o(0x607C, 0, "home offset", "i32", "rw", 0),
    _o(0x607D, 1, "software position limit: min", "i32", "rw", -300000),
    _o(0x607D, 2, "software position limit: max", "i32", "rw", 300000),
    _o(0x607E, 0, "polarity (bit 7 position, bit 6 velocity and torque: multiplied by -1)", "u8", "rw", 0),
    _o(0x607F, 0, "max profile velocity", "u32", "rw", 500000),
    _o(0x6080, 0, "max motor speed [1/min] (speed set-point limit, all modes)", "u32", "rw", 3000),
    _o(0x6081, 0, "profile velocity", "u32", "rw", 100000),
    _o(0x6083, 0, "profile acceleration", "u32", "rw", 2000000),
    _o(0x6084, 0, "profile deceleration", "u32", "rw", 2000000),
    _o(0x6085, 0, "quick stop deceleration", "u32", "rw", 10000000),
    _o(0x6086, 0, "motion profile type (0 trapezoid, 3 jerk limited)", "i16", "rw", 0),
    _o(0x6087, 0, "torque slope [per mille of rated torque / s]", "u32", "rw", 10000),
    _o(0x6088, 0, "torque profile type (0 linear ramp)", "i16", "rw", 0),
    _o(0x608F, 1, "position encoder resolution: encoder increments", "u32", "rw", 131072),
    _o(0x608F, 2, "position encoder resolution: motor revolutions", "u32", "rw", 1),
    _o(0x6091, 1, "gear ratio: motor revolutions", "u32", "rw", 1),
    _o(0x6091, 2, "gear ratio: shaft revolutions", "u32", "rw", 1),
    _o(0x6092, 1, "feed constant: feed", "u32", "rw", 16000),
    _o(0x6092, 2, "feed constant: shaft revolutions", "u32", "rw", 1),
    _o(0x6098, 0, "homing method", "i8", "rw", 35),
    _o(0x6099, 1, "homing speed: switch search", "u32", "rw", 20000),
    _o(0x6099, 2, "homing speed: zero search", "u32", "rw", 2000),
    _o(0x609A, 0, "homing acceleration", "u32", "rw", 500000),
    _o(0x60A4, 1, "profile jerk", "u32", "rw", 0),
    _o(0x60B1, 0, "velocity offset", "i32", "rw", 0),
    _o(0x60B2, 0, "torque offset [per mille]", "i16", "rw", 0),
    _o(0x60B8, 0, "touch probe function", "u16", "rw", 0),
    _o(0x60B9, 0, "touch probe status", "u16", "ro", 0),
    _o(0x60BA, 0, "touch probe 1 positive edge position", "i32", "ro", 0),
    _o(0x60BB, 0, "touch probe 1 negative edge position", "i32", "ro", 0),
    _o(0x60BC, 0, "touch probe 2 positive edge position", "i32", "ro", 0),
    _o(0x60BD, 0, "touch probe 2 negative edge position", "i32", "ro", 0),
    _o(0x60C0, 0, "interpolation sub mode select (0 linear)", "i16", "rw", 0),
    _o(0x60C1, 1, "interpolation data record: position set-point", "i32", "rw", 0),
    _o(0x60C2, 1, "interpolation time period: value", "u8", "rw", 1),
    _o(0x60C2, 2, "interpolation time period: index (10^index s)", "i8", "rw", -3),
    _o(0x60F4, 0, "following error actual value", "i32", "ro", 0),
    _o(0x60FD, 0, "digital inputs (bit 0 neg. limit, 1 pos. limit, 2 home, 16 / 17 probe 1 / 2, 18 STO active)", "u32",
       "ro", 0),
    _o(0x60FE, 1, "digital outputs: physical outputs (bit 0 set brake)", "u32", "rw", 1),
    _o(0x60FE, 2, "digital outputs: bit mask (bit 0: the master drives the brake)", "u32", "rw", 0),
    _o(0x60FF, 0, "target velocity", "i32", "rw", 0),
    _o(0x6502, 0, "supported drive modes", "u32", "ro", SUPPORTED_MODES_BITS),
)

SPECS: dict[tuple[int, int], ObjectSpec] = {o.key: o for o in OBJECTS}


def clamp_to_dtype(value: float, dtype: str) -> int | float:
    """Saturate to the range of a CANopen type (values shown saturated, never wrapped); ints rounded."""
    lo, hi = DTYPE_RANGES[dtype]
    if dtype == "f32":
        return float(min(max(value, lo), hi))
    v = int(round(value))
    return lo if v < lo else hi if v > hi else v


def eds_defaults(eds_path: str | Path) -> dict[tuple[int, int], int | float]:
    """Default values the EDS declares for the objects of :data:`OBJECTS` (those it has)."""
    p = Path(eds_path).resolve()
    return dict(_eds_defaults_cached(str(p), p.stat().st_mtime))


@functools.lru_cache(maxsize=8)
def _eds_defaults_cached(eds_path: str, _mtime: float) -> dict[tuple[int, int], int | float]:
    import canopen

    od = canopen.import_od(str(eds_path))
    out: dict[tuple[int, int], int | float] = {}
    for spec in OBJECTS:
        var = _od_var(od, spec.index, spec.sub)
        if var is not None and var.default is not None:
            try:
                out[spec.key] = float(var.default) if spec.dtype == "f32" else int(var.default)
            except (TypeError, ValueError):
                continue
    return out


def eds_limits(eds_path: str | Path) -> dict[tuple[int, int], tuple[float | None, float | None]]:
    """``LowLimit`` / ``HighLimit`` the EDS declares for the objects of :data:`OBJECTS` (those with either):
    key -> (low, high), ``None`` where one is absent. The drive enforces them on every write (SDO, Modbus, API),
    so that each path refuses what an SDO download of the object refuses."""
    p = Path(eds_path).resolve()
    return dict(_eds_limits_cached(str(p), p.stat().st_mtime))


@functools.lru_cache(maxsize=8)
def _eds_limits_cached(eds_path: str, _mtime: float) -> dict[tuple[int, int], tuple[float | None, float | None]]:
    from virtualaxis.eds_text import declared_limits

    declared = declared_limits(eds_path)
    out: dict[tuple[int, int], tuple[float | None, float | None]] = {}
    for spec in OBJECTS:
        texts = declared.get(spec.key)
        if texts is None:
            continue
        limits: list[float | None] = []
        for text in texts[:2]:
            try:
                limits.append(None if text is None else (float(text) if spec.dtype == "f32" else int(text, 0)))
            except ValueError:
                limits.append(None)  # (the slave's EDS check names a malformed limit; not the drive's job)
        if limits[0] is not None or limits[1] is not None:
            out[spec.key] = (limits[0], limits[1])
    return out


def missing_from_eds(eds_path: str | Path) -> list[ObjectSpec]:
    """Objects the drive implements that the EDS does not declare."""
    import canopen

    od = canopen.import_od(str(eds_path))
    return [s for s in OBJECTS if _od_var(od, s.index, s.sub) is None]


def _od_var(od, index: int, sub: int):
    if index not in od:
        return None
    obj = od[index]
    if hasattr(obj, "subindices"):  # record / array
        try:
            return obj[sub]
        except KeyError:
            return None
    return obj if sub == 0 else None
