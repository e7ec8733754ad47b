"""Monitoring of the axis travel, run once per drive cycle after the plant has advanced.

- **Hardware limit switches** (0x60FD bit 0 negative, bit 1 positive; active within
  ``[drive] limit_switch_inset_m`` of +-stroke/2): in EVERY mode (outside a homing run, which searches them
  itself) a switch reached while moving toward it stops the axis with the quick-stop deceleration 0x6085
  (OFF3, from the actual speed) and, per 0x2013, raises fault 0xFF10 / 0xFF11 (F07491 / F07492 STOP cam
  minus / plus, 0x2013 = 1, default) or warning A07491 / A07492 (0x2013 = 0, the drive stays enabled).
  While a switch is active, set-points toward it are held (position demand not further, velocity and
  torque toward it zero): the axis may move only away from the switch. A fault reset on the switch is
  allowed, so that the axis can be driven off it.
- **Overspeed**: the axis faster than :data:`OVERSPEED_FACTOR` x 0x6080 (max motor speed, as table speed)
  while the pulses are on -> fault 0x8401 (F07901), OFF2; the cause persists until the speed is back below
  the limit. (A motor back-driven far beyond its speed by an external force cannot be controlled; the
  inverter switches off, as SINAMICS does.)
- **Position objects**: 0x6064 / 0x6062 are 32-bit; a position beyond their range saturates (never wraps)
  and raises fault 0x8600 (F07493) once.
- (Following error, standstill, target reached, temperature and DC link are still in ``Drive._monitor``.)
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.statemachine import STATE

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive

S = STATE  # (the members as plain attributes; Cia402State is the type)
HM = 6
LIMIT_CODES = (0xFF10, 0xFF11)  # negative, positive switch
I32_MAX = 0x7FFFFFFF
#: overspeed limit = this x 0x6080 (SINAMICS p2162 hysteresis above the maximum speed; chosen 1.2)
OVERSPEED_FACTOR = 1.2


def homing_owns_switches(drive: Drive) -> bool:
    """A homing run in progress searches the limit switches itself (methods 1, 2, 17, 18) and answers an
    unexpected one with a homing error (statusword bits 13/12 = 1/0) and its own braking, which the limit
    switch fault must not overtake (it did: 0xFF11 instead of the homing error)."""
    return drive._mode == HM and (drive._hm.in_progress() or drive._hm.stopping_after_error(drive))


def blocked_direction(drive: Drive) -> int:
    """-1: motion toward negative is blocked (negative switch active), +1 positive, 0 none."""
    if homing_owns_switches(drive):
        return 0
    sw = drive._limit_switches
    if sw & 1:
        return -1
    if sw & 2:
        return 1
    return 0


def monitor_limit_switches(drive: Drive, x_plant_m: float, v_m_s: float) -> None:
    """Switch states, reaction on reaching a switch while moving toward it, warning bookkeeping."""
    neg, pos, _ = drive._switches(x_plant_m)
    drive._limit_switches = (1 if neg else 0) | (2 if pos else 0)
    if drive._warnings:
        for code, active in zip(LIMIT_CODES, (neg, pos), strict=True):
            if not active and code in drive._warnings:
                drive.set_warning(code, False)
    if not (neg or pos) or homing_owns_switches(drive):
        return
    if not drive._power or drive._state is not S.OPERATION_ENABLED or drive._stop is not None:
        return
    threshold = rx.standstill_threshold_m_s(drive)
    toward_neg = neg and (v_m_s < -threshold or drive._demand_v < -threshold)
    toward_pos = pos and (v_m_s > threshold or drive._demand_v > threshold)
    if not (toward_neg or toward_pos):
        return
    code = LIMIT_CODES[0] if toward_neg else LIMIT_CODES[1]
    if int(drive._obj(0x2013)) == 1:
        drive._raise_fault(code, drive._limit_switches)
    else:
        drive.set_warning(code, True)
        drive._internal_limit = True
        drive._start_stop("quick", then="resume")


def monitor_position_range(drive: Drive, x_units: float) -> None:
    """Fault 0x8600 once when the actual position leaves the 32-bit range of the position objects."""
    over = abs(x_units) > I32_MAX
    if over and not drive._position_overflow:
        drive._raise_fault(0x8600, I32_MAX if x_units > 0 else -I32_MAX - 1)
    drive._position_overflow = over


def monitor_overspeed(drive: Drive, v_m_s: float) -> None:
    """Fault 0x8401 (OFF2) when the axis runs faster than OVERSPEED_FACTOR x the maximum motor speed."""
    over = abs(v_m_s) > OVERSPEED_FACTOR * drive._pc.max_speed_m_s
    if over:
        if drive._power and 0x8401 not in drive._causes:
            drive._raise_fault(0x8401, int(round(v_m_s * drive._pc.inv_u)), cause="overspeed")
    elif drive._causes.get(0x8401) == "overspeed":
        del drive._causes[0x8401]
