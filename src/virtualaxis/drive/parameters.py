"""The drive parameters in SI units, computed from the objects once after a write (not every cycle):
monitoring windows and times, ratings, speed and travel limits, the interpolation period; the plant's loop
gains and current limit from the objects; the named parameters (:data:`~virtualaxis.drive.snapshot.PARAMETERS`)
and their scaling to SI units."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from virtualaxis.drive.snapshot import PARAMETERS

if TYPE_CHECKING:
    from virtualaxis.config import AxisConfig
    from virtualaxis.drive.settings import DriveSettings

#: the current limit sent to the plant for a torque / current limit 0x6072 / 0x6073 of 0 [A or N]: the plant's
#: "no limit" is 0, a zero limit is zero torque (chosen: 1e-9, no torque a measurement can resolve)
ZERO_CURRENT_LIMIT = 1e-9

#: objects whose change recomputes the parameters (:func:`drive_parameters`)
PARAMETER_INDICES = frozenset({
    0x6065, 0x6066, 0x6072, 0x2006, 0x2007, 0x6067, 0x6068, 0x606D, 0x606E, 0x606F, 0x6070, 0x200A, 0x200B,
    0x6075, 0x6076, 0x607F, 0x6080, 0x608F, 0x6091, 0x6092, 0x607D, 0x60C2, 0x607E,
})


@dataclass(frozen=True, slots=True)
class DriveParameters:
    fe_window_m: float
    fe_time_s: float
    standstill_window_m: float
    standstill_time_s: float
    position_window_m: float
    position_time_s: float
    velocity_window_m_s: float
    velocity_time_s: float
    velocity_threshold_m_s: float
    velocity_threshold_time_s: float
    temperature_alarm_c: float
    temperature_fault_c: float
    dc_over_v: float
    dc_under_v: float
    rated_current_a: float
    pmsm: bool
    inv_u: float
    rated_nm: float
    rated_a: float
    max_speed_m_s: float  # 0x6080 as table speed
    max_velocity_m_s: float  # velocity targets' limit: 0x607F and 0x6080
    kt_nm_per_a: float  # torque constant (0x6077 from the currents)
    reluctance_nm_per_a2: float  # 1.5 p (L_d - L_q)
    max_torque_nm: float  # 0x6072 as torque
    travel_limits_m: tuple[float, float] | None  # 0x607D in m (None: min >= max, no limits)
    interp_cycles: int  # 0x60C2 in drive cycles


def interp_cycles(objects: dict, cycle_s: float) -> int:
    """Drive cycles per interpolation period 0x60C2 (at least 1)."""
    period = int(objects[(0x60C2, 1)]) * 10.0 ** int(objects[(0x60C2, 2)])
    return max(1, int(round(period / cycle_s)))


def travel_limits_m(objects: dict, u: float) -> tuple[float, float] | None:
    """Software position limits 0x607D in the drive's direction [m] (position polarity 0x607E bit 7: the
    master's min / max are the drive's -max / -min), None when min >= max (off)."""
    lo, hi = int(objects[(0x607D, 1)]), int(objects[(0x607D, 2)])
    if lo >= hi:
        return None
    if int(objects[(0x607E, 0)]) & 0x80:
        return -hi * u, -lo * u
    return lo * u, hi * u


def drive_parameters(objects: dict, u: float, max_speed_m_s: float, cfg: AxisConfig, settings: DriveSettings,
                     cycle_s: float) -> DriveParameters:
    """The parameters from the objects ``objects`` (``u``: metres per position unit; ``max_speed_m_s``: 0x6080
    as table speed)."""
    o, mot = objects, cfg.motor
    vdc_nom = cfg.inverter.dc_link_v
    window = int(o[(0x6065, 0)])
    return DriveParameters(
        fe_window_m=math.inf if window == 0xFFFFFFFF else window * u,
        fe_time_s=int(o[(0x6066, 0)]) / 1000.0,
        standstill_window_m=int(o[(0x2006, 0)]) * u,
        standstill_time_s=int(o[(0x2007, 0)]) / 1000.0,
        position_window_m=int(o[(0x6067, 0)]) * u,
        position_time_s=int(o[(0x6068, 0)]) / 1000.0,
        velocity_window_m_s=int(o[(0x606D, 0)]) * u,
        velocity_time_s=int(o[(0x606E, 0)]) / 1000.0,
        velocity_threshold_m_s=int(o[(0x606F, 0)]) * u,
        velocity_threshold_time_s=int(o[(0x6070, 0)]) / 1000.0,
        temperature_alarm_c=float(o[(0x200A, 0)]),
        temperature_fault_c=float(o[(0x200B, 0)]),
        dc_over_v=settings.dc_link_overvoltage_v or 1.25 * vdc_nom,
        dc_under_v=settings.dc_link_undervoltage_v or 0.70 * vdc_nom,
        rated_current_a=mot.rated_current_a,
        pmsm=cfg.actuator.kind == "pmsm",
        inv_u=1.0 / u,
        rated_nm=float(o[(0x6076, 0)]) / 1000.0,
        rated_a=float(o[(0x6075, 0)]) / 1000.0,
        max_speed_m_s=max_speed_m_s,
        max_velocity_m_s=min(float(o[(0x607F, 0)]) * u, max_speed_m_s),
        kt_nm_per_a=mot.kt_nm_per_a,
        reluctance_nm_per_a2=1.5 * mot.pole_pairs * (mot.ld_h - mot.lq_h),
        max_torque_nm=float(o[(0x6072, 0)]) / 1000.0 * float(o[(0x6076, 0)]) / 1000.0,
        travel_limits_m=travel_limits_m(o, u),
        interp_cycles=interp_cycles(o, cycle_s),
    )


def loop_gains(objects: dict, cfg: AxisConfig, max_speed_m_s: float) -> dict[str, float | None]:
    """The plant's loop parameters from 0x2000 - 0x2004 (``AxisSimulator.set_loop_gains`` arguments)."""
    o = objects
    mode = int(o[(0x2002, 0)])
    kp = float(o[(0x2003, 0)])
    return {
        "kv_per_s": float(o[(0x2000, 0)]) * 1000.0 / 60.0,
        "velocity_ff_factor": float(o[(0x2001, 0)]) if mode >= 1 else 0.0,
        "torque_ff_factor": (cfg.control.torque_ff_factor or 1.0) if mode == 2 else 0.0,
        "speed_kp": kp if kp > 0 else None,
        "speed_ti_s": float(o[(0x2004, 0)]) / 1000.0,
        "speed_limit_m_s": max_speed_m_s,
    }


def current_limit(objects: dict, cfg: AxisConfig, kt_nm_per_a: float, power_unit_limit: float) -> float:
    """The plant's current limit [A] (a force actuator: force [N]) from 0x6072 / 0x6073 / 0x6075 / 0x6076, never
    beyond the power unit's ``power_unit_limit``; a limit of 0 is zero torque (:data:`ZERO_CURRENT_LIMIT`)."""
    o = objects
    rated_nm = float(o[(0x6076, 0)]) / 1000.0
    if cfg.actuator.kind == "pmsm":
        rated_a = float(o[(0x6075, 0)]) / 1000.0
        lim_current = float(o[(0x6073, 0)]) / 1000.0 * rated_a
        kt = kt_nm_per_a
        lim_torque_as_current = float(o[(0x6072, 0)]) / 1000.0 * rated_nm / kt if kt > 0 else lim_current
        limit = min(lim_current, lim_torque_as_current)
    else:  # force actuator: 0x6072 per mille of the rated force 0x6076 [N]
        limit = float(o[(0x6072, 0)]) / 1000.0 * rated_nm
    limit = min(limit, power_unit_limit)  # 0x6075 / 0x6076 are writable: never beyond the hardware
    # a limit of 0 is zero torque: the plant reads 0 as "no limit", so it gets the smallest positive one
    return max(limit, ZERO_CURRENT_LIMIT)


def named_parameter(name: str):
    """The spec of the named parameter ``name`` (:data:`~virtualaxis.drive.snapshot.PARAMETERS`); KeyError with
    the closest name for an unknown one."""
    spec = PARAMETERS.get(name)
    if spec is None:
        import difflib

        hint = difflib.get_close_matches(name, list(PARAMETERS), n=1)
        raise KeyError(f"unknown drive parameter {name!r}" + (f" (did you mean {hint[0]}?)" if hint else ""))
    return spec


def parameter_scale(spec, objects: dict, u: float) -> float:
    """SI units per raw unit of a named parameter (``u``: metres per position unit)."""
    if spec.scale == "pos":
        return u
    if spec.scale == "torque_nm":
        return float(objects[(0x6076, 0)]) / 1e6  # per mille of rated mN m -> N m
    if spec.scale == "current_a":
        return float(objects[(0x6075, 0)]) / 1e6
    return 1.0
