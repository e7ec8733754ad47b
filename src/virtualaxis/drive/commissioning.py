"""The axis as commissioned: the object values that come from its config (:func:`derived_objects`), the value
ranges of the objects (option codes, the EDS's LowLimit / HighLimit, this axis' loop-gain bounds:
:func:`value_ranges`, :func:`gain_ranges`) and the drive's own rules for a write (:func:`check_write_rules`)."""

from __future__ import annotations

import math

from virtualaxis.config import AxisConfig
from virtualaxis.config.axis import max_table_speed_m_s
from virtualaxis.drive import homing as hm
from virtualaxis.drive.faults import FAULT_TABLE
from virtualaxis.drive.gain_bounds import LoopGainBounds
from virtualaxis.drive.object_table import ObjectAccessError
from virtualaxis.drive.objects import DTYPE_RANGES, SPECS, clamp_to_dtype
from virtualaxis.drive.opmodes import SUPPORTED_MODE_BITS
from virtualaxis.drive.settings import DriveSettings
from virtualaxis.drive.touch_probe import check_function as check_touch_probe_function

# SDO abort codes used by the drive's own checks
ABORT_READ_ONLY = 0x06010002
ABORT_VALUE_INVALID = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_DEVICE_STATE = 0x08000022
ABORT_NO_OBJECT = 0x06020000

#: commissioned following-error window = margin x steady lag at the maximum speed + EDS default (chosen: 1.5,
#: the usual MD36400 setting of "lag plus half again")
FE_WINDOW_MARGIN = 1.5
#: 0x2011 external force limit [N] (chosen: 1 MN, the EDS's limit of 0x2011, beyond any machine-tool axis; larger
#: values only drive the integration out of the range where the end-stop contact holds the table)
MAX_EXTERNAL_FORCE_N = 1e6
#: default software limits this far inside the hardware limit switches [m] (chosen: 1 mm, far more than the
#: position loop's overshoot at a target, less than any stroke worth the name)
SOFT_LIMIT_INSIDE_SWITCH_M = 0.001
#: the simulated machine's gear (motor revolutions, screw revolutions): the plant's motor drives the screw
MACHINE_GEAR = (1, 1)


#: option codes and other objects with a narrower range than their data type: key -> (min, max)
_VALUE_RANGES = {
    (0x605A, 0): (0, 8),
    (0x605B, 0): (0, 1),
    (0x605C, 0): (0, 1),
    (0x605D, 0): (1, 3),
    (0x605E, 0): (0, 4),  # 3 current limit, 4 voltage limit (both: the current-limit stop)
    (0x6007, 0): (0, 3),
    (0x2002, 0): (0, 2),
    (0x2012, 0): (0, 1),
    (0x2013, 0): (0, 1),
    (0x60C2, 1): (1, DTYPE_RANGES["u8"][1]),  # interpolation period 0 would make every set-point a step
    (0x60C2, 2): (-6, 0),
    (0x60C0, 0): (0, 0),  # interpolation sub-mode: linear only
    (0x2014, 3): (0, 3),
    (0x6080, 0): (1, DTYPE_RANGES["u32"][1]),  # max motor speed 0 would be no motion at all
    # accelerations / decelerations: 0 would be a stop that never ends (a quick stop at 0x6085 = 0 kept the axis
    # running at speed); refused as SDO does from the EDS's LowLimit 1
    **{(index, 0): (1, DTYPE_RANGES["u32"][1]) for index in (0x6083, 0x6084, 0x6085, 0x609A)},
    # homing speeds: 0 would be a search that never moves and never ends
    (0x6099, 1): (1, DTYPE_RANGES["u32"][1]),
    (0x6099, 2): (1, DTYPE_RANGES["u32"][1]),
}
#: objects checked by ranges alone: key (and alias) -> (min, max) of an integer value, its data type's range
#: narrowed by _VALUE_RANGES; every writable integer object without a rule of its own in check_write_rules (the
#: fast path of an RPDO's controlword and targets; anything else, and any value outside, takes the full check)
_OWN_RULES = frozenset({0x6060, 0x607E, 0x60B8, 0x6088, 0x6086, 0x6098, 0x608F, 0x6091, 0x6092, 0x2000, 0x2001, 0x2003,
                        0x2004, 0x200A, 0x200B, 0x2011, 0x2010})


def value_ranges(limits: dict[tuple[int, int], tuple[float | None, float | None]]) -> dict:
    """:data:`_VALUE_RANGES` narrowed further by ``limits`` (the EDS's LowLimit / HighLimit): key -> (min, max)."""
    out = dict(_VALUE_RANGES)
    for key, (low, high) in limits.items():
        lo, hi = out.get(key, DTYPE_RANGES[SPECS[key].dtype])
        out[key] = (lo if low is None else max(lo, low), hi if high is None else min(hi, high))
    return out


def plain_int_keys() -> frozenset[tuple[int, int]]:
    """The writable integer objects without a rule of their own in :func:`check_write_rules`."""
    return frozenset(key for key, spec in SPECS.items()
                     if spec.access != "ro" and spec.dtype != "f32" and key[0] not in _OWN_RULES)


def gain_ranges(ranges: dict, b: LoopGainBounds) -> dict[tuple[int, int], str]:
    """Narrow ``ranges`` (in place) by this axis' loop-gain bounds (speed Kp 0x2003, Kv 0x2000); returns the
    reason told with a value refused by them, per object."""
    reasons = {
        (0x2003, 0): (f" (this axis' bound: speed-loop crossover Kp / J <= {b.speed_crossover_max_rad_s:.0f} "
                      f"rad/s, half of min(current-loop bandwidth {b.current_bandwidth_rad_s:.0f} rad/s, "
                      f"speed-cycle Nyquist), J = {b.inertia:.4g})"),
        (0x2000, 0): (f" (this axis' bound: Kv <= {b.kv_max_per_s:.0f} 1/s, a quarter of min(speed-loop "
                      "crossover bound, position-cycle Nyquist))"),
    }
    for key, high in (((0x2003, 0), b.speed_kp_max), ((0x2000, 0), b.kv_max_1000_per_min)):
        lo, hi = ranges.get(key, DTYPE_RANGES[SPECS[key].dtype])
        if high < hi:
            ranges[key] = (lo, high)
        else:
            del reasons[key]
    return reasons


def power_unit_limit(cfg: AxisConfig) -> float:
    """The largest current the power unit gives [A] (a force actuator: force [N]): the config's
    ``control.current_limit_a`` (else 3 x rated current; a force actuator's ``actuator.force_limit_n``, else
    none), whatever 0x6072 / 0x6073 / 0x6075 / 0x6076 hold."""
    if cfg.actuator.kind == "force":
        return cfg.actuator.force_limit_n if cfg.actuator.force_limit_n > 0 else math.inf
    c = cfg.control
    return c.current_limit_a if c.current_limit_a > 0 else 3.0 * cfg.motor.rated_current_a

def lead_m(cfg: AxisConfig) -> float:
    """Table travel per driving-shaft revolution (a direct drive uses a virtual 10 mm 'revolution')."""
    return cfg.mechanics.lead_m if cfg.mechanics.lead_m > 0 else 0.01


def switch_positions_m(cfg: AxisConfig, st: DriveSettings) -> tuple[float, float, float]:
    """Plant positions where the negative / positive limit switch and the home switch act [m]: the limit switches
    ``limit_switch_inset_m`` inside the ends of the stroke."""
    half, inset = cfg.axis.stroke_m / 2, st.limit_switch_inset_m
    return -half + inset, half - inset, st.home_switch_position_m


def commissioned_travel_m(cfg: AxisConfig, switch_at_m: tuple[float, float, float]) -> tuple[float, float]:
    """The default software limits 0x607D [m]: the config's ``limits.travel_*_m``, kept
    :data:`SOFT_LIMIT_INSIDE_SWITCH_M` inside the hardware limit switches (a commissioned axis reaches
    every target 0x607D allows without tripping a switch; seed 000's config has +-300 mm, its switches act
    at +-298 mm)."""
    lo, hi = cfg.limits.travel_min_m, cfg.limits.travel_max_m
    neg, pos, _ = switch_at_m
    lo2, hi2 = max(lo, neg + SOFT_LIMIT_INSIDE_SWITCH_M), min(hi, pos - SOFT_LIMIT_INSIDE_SWITCH_M)
    return (lo2, hi2) if lo2 < hi2 else (lo, hi)

def derived_objects(cfg: AxisConfig, st: DriveSettings, eds_defaults: dict, switch_at_m: tuple[float, float, float]
                    ) -> dict[tuple[int, int], int | float]:
    """Objects whose values come from the axis config (written at boot and on NMT reset node); ``switch_at_m``:
    the plant positions of the negative / positive limit switch and the home switch [m]."""
    c, mot = cfg.control, cfg.motor
    force = cfg.actuator.kind == "force"
    lead = lead_m(cfg)
    unit = st.position_unit_m
    rated_torque = mot.rated_torque_nm or (mot.torque_constant_nm_per_a * mot.rated_current_a)
    if force:
        rated_torque = cfg.actuator.force_limit_n / 3 if cfg.actuator.force_limit_n > 0 else 1000.0
    i_lim = c.current_limit_a if c.current_limit_a > 0 else 3.0 * mot.rated_current_a
    ff_mode = 2 if c.torque_ff_factor > 0 else (1 if c.velocity_ff_factor > 0 else 0)
    enc = cfg.sensors.motor_encoder_counts_per_rev or (1 << 20)
    travel_min_m, travel_max_m = commissioned_travel_m(cfg, switch_at_m)
    out: dict[tuple[int, int], int | float] = {
        (0x2000, 0): c.kv_1_per_s * 60.0 / 1000.0,
        (0x2001, 0): float(c.velocity_ff_factor),
        (0x2002, 0): ff_mode,
        (0x2003, 0): float(c.velocity_kp_n_s_per_m if force else c.speed_kp_nm_s_per_rad),
        (0x2004, 0): c.speed_ti_s * 1000.0,
        (0x2012, 0): 1 if st.software_limit_reaction == "fault" else 0,
        (0x6075, 0): int(round(mot.rated_current_a * 1000)),
        (0x6076, 0): int(round(rated_torque * 1000)),
        (0x6073, 0): clamp_to_dtype(i_lim / mot.rated_current_a * 1000, "u16"),
        (0x6072, 0): clamp_to_dtype(i_lim / mot.rated_current_a * 1000, "u16"),
        (0x608F, 1): int(enc),
        (0x608F, 2): 1,
        (0x6091, 1): 1,
        (0x6091, 2): 1,
        (0x6092, 1): int(round(lead / unit)),
        (0x6092, 2): 1,
        (0x607D, 1): clamp_to_dtype(travel_min_m / unit, "i32"),
        (0x607D, 2): clamp_to_dtype(travel_max_m / unit, "i32"),
        (0x607F, 0): clamp_to_dtype(cfg.limits.max_velocity_m_s / unit, "u32"),
        (0x6080, 0): default_max_motor_speed_rpm(cfg),
        (0x6502, 0): sum(SUPPORTED_MODE_BITS.values()),
    }
    if st.following_error_tolerance_m is not None:
        out[(0x6065, 0)] = clamp_to_dtype(st.following_error_tolerance_m / unit, "u32")
    else:
        out[(0x6065, 0)] = clamp_to_dtype(commissioned_fe_window_m(cfg, st, eds_defaults, out) / unit, "u32")
    if st.following_error_time_ms is not None:
        out[(0x6066, 0)] = st.following_error_time_ms
    if st.positioning_window_m is not None:
        out[(0x6067, 0)] = clamp_to_dtype(st.positioning_window_m / unit, "u32")
    if st.positioning_time_ms is not None:
        out[(0x6068, 0)] = st.positioning_time_ms
    return out

def commissioned_fe_window_m(cfg: AxisConfig, st: DriveSettings, eds_defaults: dict, derived: dict) -> float:
    """The following-error window a commissioning engineer sets (0x6065 at boot unless ``[drive]
    following_error_tolerance_m`` is given) [m]: the steady lag at the fastest speed the defaults permit
    (0x607F limited by 0x6080) with the position-loop gain and the speed feed-forward share,
    v (1 - k_ff) / Kv, times :data:`FE_WINDOW_MARGIN`, plus the EDS default as a floor for the
    acceleration transient; so that no speed the defaults allow faults."""
    c = cfg.control
    kv = max(c.kv_1_per_s, 1e-3)
    kff = c.velocity_ff_factor if c.velocity_ff_factor > 0 else 0.0
    v_max = min(cfg.limits.max_velocity_m_s, float(derived[(0x6080, 0)]) / 60.0 * lead_m(cfg))
    lag = v_max * abs(1.0 - kff) / kv
    floor = float(eds_defaults.get((0x6065, 0), 1000)) * st.position_unit_m
    return FE_WINDOW_MARGIN * lag + floor

def default_max_motor_speed_rpm(cfg: AxisConfig) -> int:
    """0x6080 at boot: the config's speed limit ``control.speed_limit_rpm``, else
    :func:`~virtualaxis.config.axis.max_table_speed_m_s` (1.1 x ``limits.max_velocity_m_s``) in (virtual)
    motor revolutions, as a commissioned drive has it (SINAMICS p1082 = the machine's maximum). The plant's
    end stops are sized for that speed (before: 1.5 x rated speed, which an end stop sized for
    ``limits.max_velocity_m_s`` alone did not stop in time)."""
    if cfg.control.speed_limit_rpm > 0:
        return int(round(cfg.control.speed_limit_rpm))
    return int(math.ceil(max_table_speed_m_s(cfg) / lead_m(cfg) * 60.0))


def check_gear_ratio(objects: dict, sub: int, value: int) -> None:
    """0x6091 describes the machine: the simulated axis' motor drives the screw directly (one motor
    revolution per screw revolution, :data:`MACHINE_GEAR`), so only that ratio is accepted (another one
    would count motor revolutions, index pulses and 0x6080 against a gear the plant does not have)."""
    motor = value if sub == 1 else int(objects[(0x6091, 1)])
    shaft = value if sub == 2 else int(objects[(0x6091, 2)])
    m, s = MACHINE_GEAR
    if motor * s != shaft * m:
        raise ObjectAccessError(
            ABORT_VALUE_INVALID,
            f"0x6091:{sub} gear ratio {motor}:{shaft} (motor:shaft revolutions) is not this axis' {m}:{s} "
            "(the motor drives the screw directly)")


def check_write_rules(key: tuple[int, int], index: int, sub: int, value, objects: dict, gain_bounds: LoopGainBounds,
                      *, homing: bool, in_operation: bool) -> None:
    """The drive's own rules for writing ``value`` to ``key`` (beyond existence, access, type and value ranges):
    raise :class:`ObjectAccessError` if the write would be refused. ``homing``: a homing run is in progress;
    ``in_operation``: OPERATION ENABLED or QUICK STOP ACTIVE."""
    if (
        key == (0x6060, 0)
        and value != 0
        and (value not in SUPPORTED_MODE_BITS or not SUPPORTED_MODE_BITS[value] & objects[(0x6502, 0)])
    ):
        raise ObjectAccessError(ABORT_VALUE_INVALID, f"mode {value} is not supported (0x6502)")
    if key == (0x607E, 0):
        if value & ~0xC0:
            raise ObjectAccessError(ABORT_VALUE_INVALID, "polarity 0x607E: only bit 7 (position) and bit 6 "
                                    f"(velocity) are defined, not 0x{value:02X}")
        if in_operation and value != objects[(0x607E, 0)]:
            raise ObjectAccessError(ABORT_DEVICE_STATE, "polarity 0x607E cannot change in operation (OPERATION "
                                    "ENABLED / QUICK STOP ACTIVE): disable operation first")
    if key == (0x60B8, 0):
        reason = check_touch_probe_function(int(value))
        if reason is not None:
            raise ObjectAccessError(ABORT_VALUE_INVALID, reason)
    if key == (0x6088, 0) and value != 0:
        raise ObjectAccessError(ABORT_VALUE_INVALID, "torque profile type must be 0 (linear)")
    if key == (0x6086, 0) and value not in (0, 3):
        raise ObjectAccessError(ABORT_VALUE_INVALID, "motion profile type must be 0 (trapezoid) or 3 (jerk)")
    if key == (0x6098, 0):
        if value not in hm.SUPPORTED_METHODS:
            raise ObjectAccessError(ABORT_VALUE_INVALID, f"homing method {value} is not supported")
        if homing:
            raise ObjectAccessError(ABORT_DEVICE_STATE, "homing method cannot change while homing")
    if key[0] in (0x608F, 0x6091, 0x6092):
        if value <= 0:
            raise ObjectAccessError(ABORT_VALUE_TOO_LOW, f"0x{index:04X}:{sub} must be > 0")
        if in_operation:
            raise ObjectAccessError(ABORT_DEVICE_STATE, "position factor cannot change in operation")
        if key[0] == 0x6091:
            check_gear_ratio(objects, sub, value)
    if key in ((0x2000, 0), (0x2001, 0), (0x2003, 0), (0x2004, 0), (0x200A, 0), (0x200B, 0)) and value < 0:
        raise ObjectAccessError(ABORT_VALUE_TOO_LOW, f"0x{index:04X}:{sub} must be >= 0")
    if key == (0x2004, 0) and 0 < value < gain_bounds.speed_tn_min_s * 1000.0:
        b = gain_bounds
        raise ObjectAccessError(
            ABORT_VALUE_TOO_LOW,
            f"0x2004:0 speed controller Tn {value:g} ms < {b.speed_tn_min_s * 1000.0:.4g} ms (this axis' bound: "
            f"Tn >= 4 / {b.speed_crossover_max_rad_s:.0f} rad/s, the fastest speed-loop crossover; 0 = P only)")
    if key == (0x2011, 0) and abs(value) > MAX_EXTERNAL_FORCE_N:
        code = ABORT_VALUE_TOO_HIGH if value > 0 else ABORT_VALUE_TOO_LOW
        raise ObjectAccessError(code, f"0x2011 external force {value:g} N beyond +-{MAX_EXTERNAL_FORCE_N:g} N")
    if key == (0x2010, 0) and value != 0 and value not in FAULT_TABLE:
        raise ObjectAccessError(ABORT_VALUE_INVALID, f"0x{value:04X} is not a known fault code")
