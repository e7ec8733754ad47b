"""The drive parameters in SI units, computed from the objects once after a write (not every cycle):
monitoring windows and times, ratings, speed and travel limits, the interpolation period."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from virtualaxis.config import AxisConfig
    from virtualaxis.drive.settings import DriveSettings

#: objects whose change recomputes the parameters (:func:`drive_parameters`)
PARAMETER_INDICES = frozenset({
    0x6065, 0x6066, 0x6072, 0x2006, 0x2007, 0x6067, 0x6068, 0x606D, 0x606E, 0x606F, 0x6070, 0x200A, 0x200B,
    0x6075, 0x6076, 0x607F, 0x6080, 0x608F, 0x6091, 0x6092, 0x607D, 0x60C2,
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
    """Software position limits 0x607D [m], None when min >= max (off)."""
    lo, hi = int(objects[(0x607D, 1)]), int(objects[(0x607D, 2)])
    if lo >= hi:
        return None
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
