"""The common contract of the CiA 402 modes of operation, one object each (:class:`OperatingMode`). Every
method takes the drive's :class:`~virtualaxis.drive.mode_context.ModeContext` (``ctx``), the one view a mode
has of its drive:

- ``enter(ctx)``: take over the axis FROM ITS ACTUAL MOTION (a mode change while moving decelerates with
  the new mode's own deceleration; velocity and torque modes start from the actual speed / torque);
- ``cycle(ctx)``: one position-loop cycle: the mode's set-point to the plant (position + feed-forward,
  speed or torque) through the limiters of the set-point channel ``ctx.setpoints`` (``position``,
  ``velocity_limit``, ``torque``);
- ``stop(ctx, decel_m_s2)``: ramp to rest with the given deceleration (halt, controlword bit 8);
- ``controlword(ctx, old_cw, cw)``: the mode-specific controlword bits 4, 5, 6, 8 (PP set-point
  handshake, HM start / interrupt); ``on_target_position`` / ``on_target_velocity``: a target object written
  (CSP / CSV take it into their interpolators);
- ``target_reached(ctx, ax, dt)`` and ``status_bits(ctx)``: statusword bits 10 / 12 / 13, returned as a
  value; ``status_mask`` names the bits the mode defines (they replace the drive's).

Each mode object OWNS its state: the set-point generator it runs (PP / HM / no mode: the shared
:class:`ProfileGenerator`; PV: a velocity ramp; PT: the torque ramp; CSP / CSV: interpolators) and its
protocol state (PP: the set-point handshake; HM: the homing run). Each class is registered by its number
(:func:`register`); :func:`make_modes` builds a fresh set per drive at power-on reset, so the reset clears
all of it. Stops for faults / quick stop / limit switches are
not the mode's: they run in :mod:`virtualaxis.drive.reactions`, from the actual speed, whatever the mode.
The drive keeps the state machine, the objects and the monitors; the set-point channel the limiters.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import JerkFilter, PositionProfile
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext

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
    def reset(self, ctx: ModeContext, p_m: float) -> None:
        """The mode's own state at rest at ``p_m`` (before :meth:`enter`; the drive resets the generator)."""
        self.current_halt = None

    def enter(self, ctx: ModeContext) -> None:
        """Take over from the actual motion: in position control, a moving axis decelerates with
        :meth:`entry_decel_m_s2` to rest from where it is (no hard stop), else hold the demand."""
        ax = ctx.axis
        v_act = ax.velocity_m_s if ctx.powered else 0.0
        if not rx.at_standstill(ctx):
            p = ax.position_m - ctx.setpoints.zero_m + ctx.lag_m(v_act)  # bumpless: speed set-point = actual speed
            decel = max(self.entry_decel_m_s2(ctx), 1e-6)
            stop_at = p + v_act * abs(v_act) / (2.0 * decel)
            gen = self.gen
            ctx.setpoints.demand_m = p
            gen.profile.reset(p, v_act)
            gen.profile.set_target(stop_at, max(abs(v_act), 1e-9), decel, decel)
            gen.jerk.reset(p, 1)
            gen.target_m = stop_at
            ctx.setpoints.last_vff = v_act
            ctx.setpoints.set_control(CONTROL_MODE.POSITION)
            ctx.setpoints.send_position(p, v_act, 0.0)
            return
        ctx.setpoints.set_control(CONTROL_MODE.POSITION)
        ctx.setpoints.send_position(ctx.setpoints.demand_m, 0.0, 0.0)

    def entry_decel_m_s2(self, ctx: ModeContext) -> float:
        """Deceleration of a stop when the mode is entered while moving [m/s^2] (no mode: 0x6085)."""
        return float(ctx.obj(0x6085)) * ctx.u

    # ------------------------------------------------------------------ cycle
    def cycle(self, ctx: ModeContext) -> None:
        pr = self.gen.profile
        if pr.velocity_m_s == 0.0:  # hold (after a stop from motion, see enter)
            pr.set_target(pr.position_m, 1.0, 1.0, 1.0)
        self._profile_step(ctx)

    def _profile_step(self, ctx: ModeContext) -> float:
        """Step the position profile (+ jerk filter) and send it to the position loop; returns the position."""
        gen = self.gen
        p, _ = gen.profile.step()
        pf = gen.jerk.step(p)
        ctx.setpoints.position(pf, (pf - ctx.setpoints.demand_m) / ctx.cycle_s)
        return p

    def stop(self, ctx: ModeContext, decel_m_s2: float) -> None:
        """Ramp the position profile to rest with ``decel_m_s2``."""
        pr = self.gen.profile
        self.gen.brake(max(pr.a_max, 1e-9), decel_m_s2)

    # ------------------------------------------------------------------ halt (controlword bit 8)
    def slow_down_m_s2(self, ctx: ModeContext) -> float:
        """The mode's slow-down ramp, halt option 1 [m/s^2]: profile deceleration 0x6084."""
        return float(ctx.obj(0x6084)) * ctx.u

    def halt_decel_m_s2(self, ctx: ModeContext) -> float:
        """Deceleration of a halt per 0x605D [m/s^2]: 1 the mode's slow-down ramp (:meth:`slow_down_m_s2`),
        2 the quick-stop ramp 0x6085, 3 the current limit (``math.inf``: the speed set-point goes to 0 and the
        speed controller brakes at the torque limit, as the quick stop's options 3 / 7)."""
        option = int(ctx.obj(0x605D))
        if option == 3:
            return math.inf
        if option == 2:
            return float(ctx.obj(0x6085)) * ctx.u
        return self.slow_down_m_s2(ctx)

    def halt_on_current_limit(self, ctx: ModeContext) -> None:
        """One cycle of a halt on the current limit in a position profile mode (PP, HM): speed set-point 0
        until standstill, then the profile restarts at rest where the axis is (its target kept for the
        release) and position control holds it."""
        gen = self.gen
        if self.current_halt is None:
            self.current_halt = "braking"
            ctx.setpoints.set_control(CONTROL_MODE.VELOCITY)
        if self.current_halt == "braking":
            ctx.setpoints.send_velocity(0.0)
            ctx.setpoints.demand_v = 0.0
            if not rx.at_standstill(ctx):
                return
            p = ctx.axis.position_m - ctx.setpoints.zero_m
            target = gen.target_m
            gen.reset(p)
            gen.target_m = target
            ctx.setpoints.demand_m = p
            ctx.setpoints.last_vff = 0.0
            ctx.setpoints.set_control(CONTROL_MODE.POSITION)
            self.current_halt = "held"
        ctx.setpoints.position(gen.profile.position_m, 0.0)

    def release_current_halt(self, ctx: ModeContext) -> None:
        """Halt released after a halt on the current limit: the profile takes over from the actual motion
        (still braking: from the actual speed, bumpless) toward its target."""
        if self.current_halt == "braking":
            gen = self.gen
            v_act = ctx.axis.velocity_m_s
            p = ctx.axis.position_m - ctx.setpoints.zero_m + ctx.lag_m(v_act)
            target = gen.target_m
            gen.profile.reset(p, v_act)
            gen.jerk.reset(p, 1)
            gen.target_m = target
            ctx.setpoints.demand_m = p
            ctx.setpoints.last_vff = v_act
            ctx.setpoints.set_control(CONTROL_MODE.POSITION)
        self.current_halt = None

    # ------------------------------------------------------------------ objects
    def controlword(self, ctx: ModeContext, old_cw: int, cw: int) -> None:
        """Mode-specific controlword bits (4, 5, 6, 8) in OPERATION ENABLED without a stop running."""

    def on_target_position(self, ctx: ModeContext, value: int) -> None:
        """0x607A written (raw position units)."""

    def on_target_velocity(self, ctx: ModeContext) -> None:
        """0x60FF / 0x60B1 written."""

    def on_interpolation_data(self, ctx: ModeContext, value: int) -> None:
        """0x60C1:1 interpolation data record written (raw position units)."""

    # ------------------------------------------------------------------ status
    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        return False

    def status_bits(self, ctx: ModeContext) -> int:
        """Bits 12 / 13 (and 10 where the mode redefines it) in OPERATION ENABLED."""
        return 0

    def quick_stop_bits(self, ctx: ModeContext) -> int:
        """Bits 12 / 13 in QUICK STOP ACTIVE: none (the targets are ignored, no set-point is acknowledged)
        except where a bit tells the actual motion."""
        return 0


register(OperatingMode)


def make_modes(cycle_s: float, position_m: float) -> dict[int, OperatingMode]:
    """A fresh set of mode objects for one drive: 0x6060 value -> mode object (0: no mode), sharing one
    :class:`ProfileGenerator` at rest at ``position_m`` (drive coordinate [m])."""
    gen = ProfileGenerator(cycle_s, position_m)
    return {number: cls(gen) for number, cls in MODE_TYPES.items()}
