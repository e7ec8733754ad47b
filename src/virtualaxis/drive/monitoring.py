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
- (Following error, standstill, target reached, temperature and DC link are in ``Drive._monitor``.)

Each monitor is a small object whose ``check`` returns an event (:class:`FaultEvent`, :class:`CauseCleared`,
:class:`LimitSwitchEvent`) or None; the drive applies the events (``Drive._apply_monitor_event``).
"""

from __future__ import annotations

from dataclasses import dataclass

LIMIT_CODES = (0xFF10, 0xFF11)  # negative, positive switch
I32_MAX = 0x7FFFFFFF
#: overspeed limit = this x 0x6080 (SINAMICS p2162 hysteresis above the maximum speed; chosen 1.2)
OVERSPEED_FACTOR = 1.2


@dataclass(frozen=True)
class FaultEvent:
    """A monitor's finding: raise fault ``code`` with ``value``; ``cause``: a persistent cause (the fault
    reset is refused while it holds, see :class:`CauseCleared`)."""

    code: int
    value: int = 0
    cause: str = ""


@dataclass(frozen=True)
class CauseCleared:
    """The persistent cause ``cause`` of fault ``code`` is gone."""

    code: int
    cause: str


@dataclass(frozen=True)
class LimitSwitchEvent:
    """A limit switch reached while moving toward it: fault (0x2013 = 1) or warning and quick stop, staying
    enabled (0x2013 = 0)."""

    code: int  # 0xFF10 negative, 0xFF11 positive
    switches: int  # 0x60FD bits 0/1
    fault: bool


Event = FaultEvent | CauseCleared | LimitSwitchEvent


class LimitSwitchMonitor:
    """The hardware limit switches (0x60FD bits 0 / 1): :attr:`switches` as last seen; :meth:`check` returns
    the reaction to a switch reached while moving toward it (outside a homing run, which searches them)."""

    def __init__(self) -> None:
        self.switches = 0

    def blocked_direction(self, homing_owns_switches: bool) -> int:
        """-1: motion toward negative is blocked (negative switch active), +1 positive, 0 none (also while a
        homing run searches the switches)."""
        if not self.switches or homing_owns_switches:
            return 0
        return -1 if self.switches & 1 else 1

    def check(self, neg: bool, pos: bool, v_m_s: float, demand_v_m_s: float, threshold_m_s: float,
              armed: bool, fault_on_switch: bool) -> LimitSwitchEvent | None:
        """``armed``: enabled, in operation, no stop running and no homing run owning the switches."""
        self.switches = (1 if neg else 0) | (2 if pos else 0)
        if not (neg or pos) or not armed:
            return None
        toward_neg = neg and (v_m_s < -threshold_m_s or demand_v_m_s < -threshold_m_s)
        toward_pos = pos and (v_m_s > threshold_m_s or demand_v_m_s > threshold_m_s)
        if not (toward_neg or toward_pos):
            return None
        return LimitSwitchEvent(LIMIT_CODES[0] if toward_neg else LIMIT_CODES[1], self.switches, fault_on_switch)


class PositionRangeMonitor:
    """Fault 0x8600 once when the actual position leaves the 32-bit range of the position objects."""

    def __init__(self) -> None:
        self.over = False

    def check(self, x_units: float) -> FaultEvent | None:
        over = abs(x_units) > I32_MAX
        event = None
        if over and not self.over:
            event = FaultEvent(0x8600, I32_MAX if x_units > 0 else -I32_MAX - 1)
        self.over = over
        return event


class OverspeedMonitor:
    """Fault 0x8401 (OFF2) while the axis runs faster than :data:`OVERSPEED_FACTOR` x the maximum motor speed
    (a persistent cause "overspeed" until it is slower again)."""

    CAUSE = "overspeed"

    @staticmethod
    def check(v_m_s: float, max_speed_m_s: float, inv_u: float, powered: bool,
              cause_now: str | None) -> FaultEvent | CauseCleared | None:
        """``cause_now``: the persistent cause recorded for 0x8401 (None: none)."""
        if abs(v_m_s) > OVERSPEED_FACTOR * max_speed_m_s:
            if powered and cause_now is None:
                return FaultEvent(0x8401, int(round(v_m_s * inv_u)), cause=OverspeedMonitor.CAUSE)
        elif cause_now == OverspeedMonitor.CAUSE:
            return CauseCleared(0x8401, OverspeedMonitor.CAUSE)
        return None
