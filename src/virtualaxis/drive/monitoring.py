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
- **Following error** 0x6065 window / 0x6066 time, in position control only -> fault 0x8611 (F07452) with the
  following error in position units; and the **standstill monitor** (SINAMICS p2542 / p2543 as 0x2006 / 0x2007):
  the demand at rest for 0x2007, the following error beyond 0x2006 -> the same fault.
- **Motor temperature**: a first-order winding model (rated current -> :data:`MOTOR_RISE_AT_RATED_K` in steady
  state, time constant :data:`MOTOR_THERMAL_TAU_S`): alarm A07910 from 0x2021, fault 0x4310 (F07011, a persistent
  cause) from 0x2022.
- **DC link**: over- and undervoltage against the power unit's limits -> faults 0x3210 / 0x3220 (persistent causes).
- (Target reached is the mode object's, speed = 0 :class:`~virtualaxis.drive.profiles.SpeedZeroDetector`.)

Each monitor is a small object whose ``check`` returns an event (:class:`FaultEvent`, :class:`CauseCleared`,
:class:`LimitSwitchEvent`, :class:`AlarmChanged`), a tuple of events, or None; the drive applies the events
(``Drive._apply_monitor_event``) in the order the monitors run, so that a fault raised by one is seen by the next.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from virtualaxis.drive.fault_manager import MOTOR_TEMPERATURE_ALARM
from virtualaxis.drive.objects import clamp_to_dtype
from virtualaxis.drive.profiles import WindowTimer

if TYPE_CHECKING:
    from virtualaxis.drive.parameters import DriveParameters

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


@dataclass(frozen=True)
class AlarmChanged:
    """The motor-temperature alarm number shown in 0x2031 (0: none) changed."""

    number: int


Event = FaultEvent | CauseCleared | LimitSwitchEvent | AlarmChanged
#: no events (a monitor's common answer; no allocation per cycle)
NO_EVENTS: tuple[Event, ...] = ()
#: the following-error fault (F07452), also the standstill monitor's
FOLLOWING_ERROR_FAULT = 0x8611

MOTOR_AMBIENT_C = 20.0
MOTOR_RISE_AT_RATED_K = 100.0  # chosen: rated current heats the winding by 100 K in steady state
MOTOR_THERMAL_TAU_S = 600.0  # chosen: winding thermal time constant
MOTOR_TEMPERATURE_CAUSE = "motor temperature"
DC_LINK_CAUSE = "dc link"


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


class FollowingErrorMonitor:
    """Following error 0x6065 / 0x6066 against the window timer the mode objects read (``ModeContext.fe_timer``:
    PP shows bit 13 from it)."""

    @staticmethod
    def check(fe_m: float, timer: WindowTimer, dt_s: float, pc: DriveParameters) -> tuple[bool, FaultEvent | None]:
        """In position control: (exceeded, fault 0x8611 while exceeded)."""
        exceeded = timer.update(abs(fe_m) > pc.fe_window_m, dt_s, pc.fe_time_s)
        if exceeded:
            return True, FaultEvent(FOLLOWING_ERROR_FAULT, clamp_to_dtype(fe_m * pc.inv_u, "i32"))
        return False, None


class StandstillMonitor:
    """The demand at rest for 0x2007 in position control, the following error beyond 0x2006 in OPERATION
    ENABLED -> fault 0x8611."""

    def __init__(self) -> None:
        self.timer = WindowTimer()

    def check(self, fe_m: float, dt_s: float, pc: DriveParameters, demand_at_rest: bool,
              operation_enabled: bool) -> FaultEvent | None:
        """``demand_at_rest``: position control, the demand speed 0 and no stop running."""
        timer = self.timer
        if not demand_at_rest:
            if timer.held_s:
                timer.held_s = 0.0
            return None
        at_rest = timer.update(True, dt_s, pc.standstill_time_s)
        if at_rest and abs(fe_m) > pc.standstill_window_m and operation_enabled:
            return FaultEvent(FOLLOWING_ERROR_FAULT, clamp_to_dtype(fe_m * pc.inv_u, "i32"))
        return None


class MotorTemperature:
    """The winding temperature model and its alarm (0x2021) and fault (0x2022) thresholds."""

    def __init__(self) -> None:
        self.rise_k = 0.0  # above ambient [K]

    @property
    def temperature_c(self) -> float:
        return MOTOR_AMBIENT_C + self.rise_k

    def add_heat(self, rise_k: float) -> None:
        self.rise_k += rise_k

    def check(self, current_q_a: float, current_d_a: float, dt_s: float, pc: DriveParameters, alarm_now: int,
              cause_now: str | None) -> tuple[Event, ...]:
        """One cycle of the model (with the currents of a PMSM; a force actuator keeps its temperature), then the
        alarm's change and the fault or its cause gone. ``alarm_now``: the alarm shown; ``cause_now``: the
        persistent cause recorded for 0x4310."""
        if pc.pmsm:
            i2 = current_q_a * current_q_a + current_d_a * current_d_a
            rise_ss = MOTOR_RISE_AT_RATED_K * i2 / (pc.rated_current_a * pc.rated_current_a)
            self.rise_k += dt_s / MOTOR_THERMAL_TAU_S * (rise_ss - self.rise_k)
        temp = MOTOR_AMBIENT_C + self.rise_k
        alarm = MOTOR_TEMPERATURE_ALARM if temp >= pc.temperature_alarm_c else 0
        if temp >= pc.temperature_fault_c:
            fault: Event | None = (FaultEvent(0x4310, int(temp * 10), cause=MOTOR_TEMPERATURE_CAUSE)
                                   if cause_now is None else None)
        elif cause_now == MOTOR_TEMPERATURE_CAUSE:
            fault = CauseCleared(0x4310, MOTOR_TEMPERATURE_CAUSE)
        else:
            fault = None
        if alarm != alarm_now:
            return (AlarmChanged(alarm),) if fault is None else (AlarmChanged(alarm), fault)
        return NO_EVENTS if fault is None else (fault,)


class DcLinkMonitor:
    """DC-link over- (0x3210) and undervoltage (0x3220), each a persistent cause while it lasts."""

    CODES = (0x3210, 0x3220)

    @staticmethod
    def check(vdc_v: float, pc: DriveParameters, causes: dict[int, str]) -> tuple[Event, ...]:
        over, under = vdc_v > pc.dc_over_v, vdc_v < pc.dc_under_v
        if not (over or under or causes):
            return NO_EVENTS
        events: list[Event] = []
        for code, bad in ((0x3210, over), (0x3220, under)):
            if bad and code not in causes:
                events.append(FaultEvent(code, int(vdc_v * 1000), cause=DC_LINK_CAUSE))
            elif not bad and causes.get(code) == DC_LINK_CAUSE:
                events.append(CauseCleared(code, DC_LINK_CAUSE))
        return tuple(events)
