"""The common contract of the CiA 402 modes of operation, one object each (:class:`OperatingMode`):

- ``enter(drive)``: take over the axis FROM ITS ACTUAL MOTION (a mode change while moving decelerates with
  the new mode's own deceleration; velocity and torque modes start from the actual speed / torque);
- ``cycle(drive)``: one position-loop cycle: the mode's set-point to the plant (position + feed-forward,
  speed or torque) through the drive's set-point limiters (``Drive._set_position``, ``_velocity_limit``,
  ``_apply_torque``);
- ``stop(drive, decel_m_s2)``: ramp to rest with the given deceleration (halt, controlword bit 8);
- ``controlword(drive, old_cw, cw)``: the mode-specific controlword bits 4, 5, 6, 8 (PP set-point
  handshake, HM start / interrupt); ``on_target_position`` / ``on_target_velocity``: a target object written
  (CSP / CSV take it into their interpolators);
- ``target_reached(drive, ax, dt)`` and ``status_bits(drive)``: statusword bits 10 / 12 / 13, returned as a
  value; ``status_mask`` names the bits the mode defines (they replace the drive's).

Each mode object OWNS its state: the set-point generator it runs (PP / HM / no mode: the shared
:class:`ProfileGenerator`; PV: a velocity ramp; PT: the torque ramp; CSP / CSV: interpolators) and its
protocol state (PP: the set-point handshake; HM: the homing run). Each class is registered by its number
(:func:`register`); :func:`make_modes` builds a fresh set per drive at power-on reset, so the reset clears
all of it. Stops for faults / quick stop / limit switches are
not the mode's: they run in :mod:`virtualaxis.drive.reactions`, from the actual speed, whatever the mode.
The drive keeps the state machine, the objects, the set-point limiting and the monitors.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import JerkFilter, PositionProfile
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive

#: the mode classes by 0x6060 value (:func:`register`)
MODE_TYPES: dict[OperationMode, type[OperatingMode]] = {}


def register(cls: type[OperatingMode]) -> type[OperatingMode]:
    """Class decorator: the mode class for its ``number`` (one class per number)."""
    if cls.number in MODE_TYPES:
        raise ValueError(f"mode {cls.number!r} registered twice")
    MODE_TYPES[cls.number] = cls
    return cls


class ProfileGenerator:
    """The position set-point generator of the profile modes (no mode, PP, HM): online trapezoid
    (:class:`PositionProfile`) + jerk filter, and the end point it is commanded to (``target_m``, drive
    coordinate [m]). One instance per drive, shared by those modes (a mode change hands it over)."""

    def __init__(self, cycle_s: float, position_m: float):
        self.profile = PositionProfile(cycle_s, position_m)
        self.jerk = JerkFilter()
        self.jerk.reset(position_m, 1)
        self.target_m = position_m

    def reset(self, position_m: float) -> None:
        """At rest at ``position_m`` (profile, jerk filter and target)."""
        self.profile.reset(position_m, 0.0)
        self.jerk.reset(position_m, 1)
        self.target_m = position_m

    def settled(self) -> bool:
        """Profile at its target and the jerk filter drained [-]."""
        return self.profile.done and self.jerk.settled(self.profile.position_m)

    def brake(self, a_m_s2: float, d_m_s2: float) -> None:
        """Re-target to stop from the present profile speed with deceleration ``d_m_s2`` [m/s^2]."""
        pr = self.profile
        pv = pr.velocity_m_s
        pr.set_target(pr.position_m + pv * abs(pv) / (2 * d_m_s2), max(abs(pv), 1e-9), a_m_s2, d_m_s2)


class OperatingMode:
    """Common contract; the base class is "no mode" (0x6060 = 0): hold the position."""

    number = OperationMode.NO_MODE
    #: the statusword bits the mode defines in OPERATION ENABLED (its :meth:`status_bits` replace them)
    status_mask = 0x3000
    control = CONTROL_MODE.POSITION

    def __init__(self, gen: ProfileGenerator):
        self.gen = gen
        #: halt on the current limit (0x605D = 3): None, "braking" (speed set-point 0) or "held" (at rest)
        self.current_halt: str | None = None

    # ------------------------------------------------------------------ enter
    def reset(self, d: Drive, p_m: float) -> None:
        """The mode's own state at rest at ``p_m`` (before :meth:`enter`; the drive resets the generator)."""
        self.current_halt = None

    def enter(self, d: Drive) -> None:
        """Take over from the actual motion: in position control, a moving axis decelerates with
        :meth:`entry_decel_m_s2` to rest from where it is (no hard stop), else hold the demand."""
        ax = d._axis
        v_act = ax.velocity_m_s if d._power else 0.0
        if not rx.at_standstill(d):
            p = ax.position_m - d.setpoints.zero_m + d._lag_m(v_act)  # bumpless: speed set-point = actual speed
            decel = max(self.entry_decel_m_s2(d), 1e-6)
            stop_at = p + v_act * abs(v_act) / (2.0 * decel)
            gen = self.gen
            d.setpoints.demand_m = p
            gen.profile.reset(p, v_act)
            gen.profile.set_target(stop_at, max(abs(v_act), 1e-9), decel, decel)
            gen.jerk.reset(p, 1)
            gen.target_m = stop_at
            d.setpoints.last_vff = v_act
            d.setpoints.set_control(CONTROL_MODE.POSITION)
            d.setpoints.send_position(p, v_act, 0.0)
            return
        d.setpoints.set_control(CONTROL_MODE.POSITION)
        d.setpoints.send_position(d.setpoints.demand_m, 0.0, 0.0)

    def entry_decel_m_s2(self, d: Drive) -> float:
        """Deceleration of a stop when the mode is entered while moving [m/s^2] (no mode: 0x6085)."""
        return float(d._obj(0x6085)) * d._u

    # ------------------------------------------------------------------ cycle
    def cycle(self, d: Drive) -> None:
        pr = self.gen.profile
        if pr.velocity_m_s == 0.0:  # hold (after a stop from motion, see enter)
            pr.set_target(pr.position_m, 1.0, 1.0, 1.0)
        self._profile_step(d)

    def _profile_step(self, d: Drive) -> float:
        """Step the position profile (+ jerk filter) and send it to the position loop; returns the position."""
        gen = self.gen
        p, _ = gen.profile.step()
        pf = gen.jerk.step(p)
        d._set_position(pf, (pf - d.setpoints.demand_m) / d.cycle_s)
        return p

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        """Ramp the position profile to rest with ``decel_m_s2``."""
        pr = self.gen.profile
        self.gen.brake(max(pr.a_max, 1e-9), decel_m_s2)

    # ------------------------------------------------------------------ halt (controlword bit 8)
    def slow_down_m_s2(self, d: Drive) -> float:
        """The mode's slow-down ramp, halt option 1 [m/s^2]: profile deceleration 0x6084."""
        return float(d._obj(0x6084)) * d._u

    def halt_decel_m_s2(self, d: Drive) -> float:
        """Deceleration of a halt per 0x605D [m/s^2]: 1 the mode's slow-down ramp (:meth:`slow_down_m_s2`),
        2 the quick-stop ramp 0x6085, 3 the current limit (``math.inf``: the speed set-point goes to 0 and the
        speed controller brakes at the torque limit, as the quick stop's options 3 / 7)."""
        option = int(d._obj(0x605D))
        if option == 3:
            return math.inf
        if option == 2:
            return float(d._obj(0x6085)) * d._u
        return self.slow_down_m_s2(d)

    def halt_on_current_limit(self, d: Drive) -> None:
        """One cycle of a halt on the current limit in a position profile mode (PP, HM): speed set-point 0
        until standstill, then the profile restarts at rest where the axis is (its target kept for the
        release) and position control holds it."""
        gen = self.gen
        if self.current_halt is None:
            self.current_halt = "braking"
            d.setpoints.set_control(CONTROL_MODE.VELOCITY)
        if self.current_halt == "braking":
            d.setpoints.send_velocity(0.0)
            d.setpoints.demand_v = 0.0
            if not rx.at_standstill(d):
                return
            p = d._axis.position_m - d.setpoints.zero_m
            target = gen.target_m
            gen.reset(p)
            gen.target_m = target
            d.setpoints.demand_m = p
            d.setpoints.last_vff = 0.0
            d.setpoints.set_control(CONTROL_MODE.POSITION)
            self.current_halt = "held"
        d._set_position(gen.profile.position_m, 0.0)

    def release_current_halt(self, d: Drive) -> None:
        """Halt released after a halt on the current limit: the profile takes over from the actual motion
        (still braking: from the actual speed, bumpless) toward its target."""
        if self.current_halt == "braking":
            gen = self.gen
            v_act = d._axis.velocity_m_s
            p = d._axis.position_m - d.setpoints.zero_m + d._lag_m(v_act)
            target = gen.target_m
            gen.profile.reset(p, v_act)
            gen.jerk.reset(p, 1)
            gen.target_m = target
            d.setpoints.demand_m = p
            d.setpoints.last_vff = v_act
            d.setpoints.set_control(CONTROL_MODE.POSITION)
        self.current_halt = None

    # ------------------------------------------------------------------ objects
    def controlword(self, d: Drive, old_cw: int, cw: int) -> None:
        """Mode-specific controlword bits (4, 5, 6, 8) in OPERATION ENABLED without a stop running."""

    def on_target_position(self, d: Drive, value: int) -> None:
        """0x607A written (raw position units)."""

    def on_target_velocity(self, d: Drive) -> None:
        """0x60FF / 0x60B1 written."""

    # ------------------------------------------------------------------ status
    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        """Bits 12 / 13 (and 10 where the mode redefines it) in OPERATION ENABLED."""
        return 0

    def quick_stop_bits(self, d: Drive) -> int:
        """Bits 12 / 13 in QUICK STOP ACTIVE: none (the targets are ignored, no set-point is acknowledged)
        except where a bit tells the actual motion."""
        return 0


register(OperatingMode)


def make_modes(cycle_s: float, position_m: float) -> dict[int, OperatingMode]:
    """A fresh set of mode objects for one drive: 0x6060 value -> mode object (0: no mode), sharing one
    :class:`ProfileGenerator` at rest at ``position_m`` (drive coordinate [m])."""
    gen = ProfileGenerator(cycle_s, position_m)
    return {number: cls(gen) for number, cls in MODE_TYPES.items()}
