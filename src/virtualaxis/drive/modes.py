"""The CiA 402 modes of operation, one object each, with one small contract (:class:`OperatingMode`):

- ``enter(drive)``: take over the axis FROM ITS ACTUAL MOTION (a mode change while moving decelerates with
  the new mode's own deceleration; velocity and torque modes start from the actual speed / torque);
- ``cycle(drive)``: one position-loop cycle: the mode's set-point to the plant (position + feed-forward,
  speed or torque) through the drive's set-point limiters (``Drive._set_position``, ``_velocity_limit``,
  ``_apply_torque``);
- ``stop(drive, decel_m_s2)``: ramp to rest with the given deceleration (halt, controlword bit 8);
- ``controlword(drive, old_cw, cw)``: the mode-specific controlword bits 4, 5, 6, 8 (PP set-point
  handshake, HM start / interrupt); ``on_target_position`` / ``on_target_velocity``: a target object written
  (CSP / CSV take it into their interpolators);
- ``target_reached(drive, ax, dt)`` and ``status_bits(drive)``: statusword bits 10 / 12 / 13.

Each mode object OWNS its state: the set-point generator it runs (PP / HM / no mode: the shared
:class:`ProfileGenerator`; PV: a velocity ramp; PT: the torque ramp; CSP / CSV: interpolators) and its
protocol state (PP: the set-point handshake; HM: the homing run). :func:`make_modes` builds a fresh set per
drive at power-on reset, so the reset clears all of it. Stops for faults / quick stop / limit switches are
not the mode's: they run in :mod:`virtualaxis.drive.reactions`, from the actual speed, whatever the mode.
The drive keeps the state machine, the objects, the set-point limiting and the monitors.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive import homing as hm
from virtualaxis.drive import reactions as rx
from virtualaxis.drive.profiles import (
    MAX_JERK_FILTER_CYCLES,
    JerkFilter,
    LinearInterpolator,
    PositionProfile,
    VelocityRamp,
)
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive

PP, PV, PT, HM, CSP, CSV, CST = 1, 3, 4, 6, 8, 9, 10
_ACTIVE_HOMING = (hm.HomingStatus.IN_PROGRESS, hm.HomingStatus.RETURNING)
#: homing: the last stretch before a switch edge is crossed at the zero search speed 0x6099:2 [m] (chosen: 2 mm,
#: the edge is latched at that speed as on a drive that creeps over the cam)
HOMING_CRAWL_M = 0.002


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

    number = 0
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
            p = ax.position_m - d._zero_m + d._lag_m(v_act)  # bumpless: speed set-point = actual speed
            decel = max(self.entry_decel_m_s2(d), 1e-6)
            stop_at = p + v_act * abs(v_act) / (2.0 * decel)
            gen = self.gen
            d._demand_m = p
            gen.profile.reset(p, v_act)
            gen.profile.set_target(stop_at, max(abs(v_act), 1e-9), decel, decel)
            gen.jerk.reset(p, 1)
            gen.target_m = stop_at
            d._last_vff = v_act
            d._set_sim_mode(CONTROL_MODE.POSITION)
            d.sim.set_position_setpoint(p + d._zero_m, v_act, 0.0)
            return
        d._set_sim_mode(CONTROL_MODE.POSITION)
        d.sim.set_position_setpoint(d._demand_m + d._zero_m, 0.0, 0.0)

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
        d._set_position(pf, (pf - d._demand_m) / d.cycle_s)
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
            d._set_sim_mode(CONTROL_MODE.VELOCITY)
        if self.current_halt == "braking":
            d.sim.set_velocity_setpoint(0.0)
            d._demand_v = 0.0
            if not rx.at_standstill(d):
                return
            p = d._axis.position_m - d._zero_m
            target = gen.target_m
            gen.reset(p)
            gen.target_m = target
            d._demand_m = p
            d._last_vff = 0.0
            d._set_sim_mode(CONTROL_MODE.POSITION)
            self.current_halt = "held"
        d._set_position(gen.profile.position_m, 0.0)

    def release_current_halt(self, d: Drive) -> None:
        """Halt released after a halt on the current limit: the profile takes over from the actual motion
        (still braking: from the actual speed, bumpless) toward its target."""
        if self.current_halt == "braking":
            gen = self.gen
            v_act = d._axis.velocity_m_s
            p = d._axis.position_m - d._zero_m + d._lag_m(v_act)
            target = gen.target_m
            gen.profile.reset(p, v_act)
            gen.jerk.reset(p, 1)
            gen.target_m = target
            d._demand_m = p
            d._last_vff = v_act
            d._set_sim_mode(CONTROL_MODE.POSITION)
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


class ProfilePosition(OperatingMode):
    """PP (1): trapezoid / jerk-limited profile to 0x607A with the set-point handshake (bits 4, 5, 6)."""

    number = PP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.ack = False  # statusword bit 12 "set-point acknowledge"
        self.pending_m: float | None = None  # buffered set-point (single set-point, not change immediately)
        self.halting = False  # the halt's braking profile is planned (once, when bit 8 rises)

    def reset(self, d: Drive, p_m: float) -> None:
        super().reset(d, p_m)
        self.ack = False
        self.pending_m = None
        self.halting = False

    def entry_decel_m_s2(self, d: Drive) -> float:
        return float(d._obj(0x6084)) * d._u

    def limits(self, d: Drive) -> tuple[float, float, float]:
        """Profile velocity (0x6081 limited by 0x607F and 0x6080), acceleration 0x6083, deceleration 0x6084
        [m/s, m/s^2, m/s^2]."""
        o, u = d.objects, d._u
        v = min(float(o[(0x6081, 0)]), float(o[(0x607F, 0)])) * u
        return min(v, d._params().max_speed_m_s), float(o[(0x6083, 0)]) * u, float(o[(0x6084, 0)]) * u

    def cycle(self, d: Drive) -> None:
        gen = self.gen
        halt = bool(d._cw & 0x100)
        v, a, dec = self.limits(d)
        if halt:
            decel = self.halt_decel_m_s2(d)
            if math.isinf(decel) or self.current_halt is not None:
                self.halt_on_current_limit(d)
                return
            if not self.halting:  # planned once: re-planned every cycle it braked at about half of 0x6084
                gen.brake(a, decel)
                self.halting = True
        else:
            if self.current_halt is not None:
                self.release_current_halt(d)
            self.halting = False
            gen.profile.set_target(gen.target_m, v, a, dec)
        p = self._profile_step(d)
        if not halt and self.pending_m is not None and gen.profile.done and gen.jerk.settled(p):
            gen.target_m = self.pending_m
            self.pending_m = None
            self.start_move(d)
            if not d._cw & 0x10:
                self.ack = False

    @staticmethod
    def jerk_cycles(d: Drive) -> int:
        """Length of the jerk filter a set-point gets now [drive cycles]: T_j = 0x6083 / 0x60A4 with 0x6086 = 3,
        else 1 (may exceed :data:`MAX_JERK_FILTER_CYCLES`: such a set-point cannot be planned)."""
        o = d.objects
        jerk = float(o[(0x60A4, 1)])
        if int(o[(0x6086, 0)]) != 3 or jerk <= 0:
            return 1
        cycles = float(o[(0x6083, 0)]) / jerk / d.cycle_s
        return MAX_JERK_FILTER_CYCLES + 1 if cycles > MAX_JERK_FILTER_CYCLES else max(1, int(round(cycles)))

    def plannable(self, d: Drive) -> bool:
        """Whether a set-point can be planned with the present profile objects; if not, it is refused
        (:meth:`Drive.refuse_setpoint`: warning EMCY, SDO abort) and the axis stays where the profile is."""
        n = self.jerk_cycles(d)
        if n <= MAX_JERK_FILTER_CYCLES:
            return True
        acc, jerk = int(d.objects[(0x6083, 0)]), int(d.objects[(0x60A4, 1)])
        d.refuse_setpoint(
            f"set-point not planned: jerk time T_j = 0x6083 / 0x60A4 = {acc} / {jerk} = {acc / jerk:g} s is longer "
            f"than {MAX_JERK_FILTER_CYCLES} drive cycles ({MAX_JERK_FILTER_CYCLES * d.cycle_s:g} s)")
        return False

    def start_move(self, d: Drive) -> None:
        """A new set-point takes effect: the jerk filter length from 0x6086 / 0x60A4 (only when at rest). One
        that cannot be planned (the profile objects changed since it was accepted) is refused: the profile
        stops where it is."""
        gen = self.gen
        pr = gen.profile
        n = self.jerk_cycles(d)
        if n > MAX_JERK_FILTER_CYCLES:
            self.plannable(d)
            gen.target_m = pr.position_m if pr.done else gen.target_m
            return
        if n > 1 and gen.jerk.settled(pr.position_m) and pr.done:
            gen.jerk.reset(pr.position_m, n)
        elif n == 1 and gen.jerk.n != 1 and gen.jerk.settled(pr.position_m):
            gen.jerk.reset(pr.position_m, 1)

    def controlword(self, d: Drive, old_cw: int, cw: int) -> None:
        """Set-point handshake: rising bit 4 takes 0x607A (bit 6 relative, bit 5 change immediately)."""
        if cw & 0x10 and not old_cw & 0x10:
            if not self.ack or cw & 0x20:
                value = int(d._obj(0x607A))
                base = self.pending_m if self.pending_m is not None else self.gen.target_m
                target = base + value * d._u if cw & 0x40 else value * d._u
                target_l = d._check_limit(target, value) if self.plannable(d) else None
                if target_l is not None:
                    d.accept_setpoint()
                    if cw & 0x20 or self.gen.settled():
                        self.gen.target_m = target_l
                        self.pending_m = None
                        self.start_move(d)
                    else:
                        self.pending_m = target_l
                    self.ack = True
                    d._restart_target_window()
        elif not cw & 0x10 and self.pending_m is None:
            self.ack = False

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        gen = self.gen
        pr = gen.profile
        if d._cw & 0x100 and pr.velocity_m_s == 0.0:  # halted
            return True
        x = ax.position_m - d._zero_m
        cond = (
            pr.done
            and self.pending_m is None
            and gen.jerk.settled(pr.position_m)
            and abs(gen.target_m - x) <= pc.position_window_m
        )
        return d._tr_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, d: Drive) -> int:
        sw = 0x1000 if self.ack else 0
        return sw | (0x2000 if d._fe_timer.held_s > 0 and d._fe_exceeded else 0)


class Homing(OperatingMode):
    """HM (6): the methods of :mod:`virtualaxis.drive.homing` on the simulated switches; ``run`` is the
    homing run in progress / last finished (None: idle or interrupted)."""

    number = HM

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.run: hm.HomingRun | None = None

    def reset(self, d: Drive, p_m: float) -> None:
        super().reset(d, p_m)
        self.run = None

    def in_progress(self) -> bool:
        return self.run is not None and self.run.status in _ACTIVE_HOMING

    def stopping_after_error(self, d: Drive) -> bool:
        """A homing run ended in a homing error (an unexpected limit switch) and the axis still brakes (its
        profile, or the actual motion behind it)."""
        return (self.run is not None and self.run.status == hm.HomingStatus.ERROR
                and (self.gen.profile.velocity_m_s != 0.0 or not rx.at_standstill(d)))

    @staticmethod
    def accel_m_s2(d: Drive) -> float:
        """Homing acceleration 0x609A [m/s^2]."""
        return max(float(d._obj(0x609A)) * d._u, 1e-6)

    def entry_decel_m_s2(self, d: Drive) -> float:
        return self.accel_m_s2(d)

    def slow_down_m_s2(self, d: Drive) -> float:
        """Halt option 1 in homing: the homing acceleration 0x609A."""
        return self.accel_m_s2(d)

    def controlword(self, d: Drive, old_cw: int, cw: int) -> None:
        """Rising bit 4 starts homing; bit 4 dropped while homing interrupts it (decelerating)."""
        if cw & 0x10 and not old_cw & 0x10:
            self.start(d)
        elif not cw & 0x10 and self.in_progress():
            self.run = None  # bit 4 dropped: homing interrupted
            pr = self.gen.profile
            pr.set_target(pr.position_m, 1, 1, self.accel_m_s2(d))

    def start(self, d: Drive) -> None:
        method = int(d._obj(0x6098))
        x = d._axis.position_m
        neg, pos, home = d._switches(x, method)
        phases = hm.method_phases(method, neg, pos, home)
        if phases is None:
            self.run = hm.HomingRun(method, [], x, status=hm.HomingStatus.ERROR, error="unsupported method")
            return
        self.run = hm.HomingRun(method, phases, x)
        d._homed = False
        self.gen.profile.reset(d._demand_m, 0.0)
        self.gen.jerk.reset(d._demand_m, 1)
        if not phases:
            self.run.home_m = x
            self.finish(d)

    def cycle(self, d: Drive) -> None:
        halt = bool(d._cw & 0x100)
        if halt and (self.current_halt is not None
                     or (self.in_progress() and math.isinf(self.halt_decel_m_s2(d)))):
            self.run = None  # halted: homing interrupted
            self.halt_on_current_limit(d)
            return
        if not halt and self.current_halt is not None:
            self.release_current_halt(d)
        self._phase_step(d, halt)
        self._profile_step(d)

    def _phase_step(self, d: Drive, halt: bool) -> None:
        """One cycle of the homing phases: the profile's target for this cycle, switch / index detection."""
        run = self.run
        pr = self.gen.profile
        acc = self.accel_m_s2(d)
        if run is None or run.status in (hm.HomingStatus.ATTAINED, hm.HomingStatus.ERROR):
            pr.set_target(pr.position_m if pr.velocity_m_s == 0 else pr.target_m, 1.0, acc, acc)
            return
        if halt:
            self.gen.brake(acc, self.halt_decel_m_s2(d))  # 0x605D: 1 homing acceleration, 2 quick-stop ramp
            self.run = None  # halted: interrupted
            return
        x_plant = d._axis.position_m
        if run.status == hm.HomingStatus.RETURNING:
            pr.set_target(run.home_m - d._zero_m, d.objects[(0x6099, 2)] * d._u, acc, acc)
            if pr.done and abs(d._axis.velocity_m_s) < 1e-4:
                self.finish(d)
            return
        phase = run.phase
        fast = float(d._obj(0x6099, 1)) * d._u
        slow = float(d._obj(0x6099, 2)) * d._u
        speed = fast if phase.fast else slow
        if not speed > 0:  # (a write refuses 0; loaded parameters are not checked): a search that never ends
            run.status = hm.HomingStatus.ERROR
            run.error = "homing speed 0x6099 is 0"
            self.gen.brake(acc, acc)
            return
        if not phase.fast and phase.signal != "index" and math.isfinite(run.edge_m):
            # back to a switch edge found at the search speed, which may have braked far past it: run at up to
            # the search speed and slow down in time to cross the edge at the zero search speed (a 500 mm/s
            # search stops 12.5 mm past the switch; at the default 10 mm/s the way back took 1.3 s)
            remaining = (run.edge_m - x_plant) * phase.direction - HOMING_CRAWL_M
            if remaining > 0:
                speed = max(slow, min(max(fast, slow), math.sqrt(slow * slow + 2 * acc * remaining)))
        far = phase.direction * 10.0 * max(d.cfg.axis.stroke_m, 0.1)
        neg, pos, home = d._switches(x_plant, run.method)
        if (neg and pr.velocity_m_s < 0) or (pos and pr.velocity_m_s > 0):
            # on a hardware limit switch and still moving into it (methods 1, 2, 17, 18 search for it): brake at
            # least with the quick-stop deceleration 0x6085, the drive's limit-switch reaction in every mode; a
            # homing acceleration made for the slow return would run the table into the end stop
            acc = max(acc, float(d._obj(0x6085)) * d._u)
        pr.set_target(pr.position_m + far, speed, acc, acc)
        hit = False
        latched = x_plant
        if phase.signal == "index":
            period = d.scaling.motor_rev_travel_m
            crossing = hm.index_crossed(d._prev_actual_m, x_plant, d.settings.index_pulse_offset_m, period)
            if crossing is not None and (crossing - d._prev_actual_m) * phase.direction > 0:
                hit, latched = True, crossing
        else:
            value = {"neg": neg, "pos": pos, "home": home}[phase.signal]
            hit = value == phase.value
        # an unexpected limit switch in the direction of travel is a homing error
        if not hit and (
            (phase.direction > 0 and pos and phase.signal != "pos")
            or (phase.direction < 0 and neg and phase.signal != "neg")
        ):
            run.status = hm.HomingStatus.ERROR
            run.error = "limit switch reached"
            self.gen.brake(acc, acc)
            return
        if hit:
            run.edge_m = latched
            run.phase_index += 1
            if run.phase is None:
                run.home_m = latched
                run.status = hm.HomingStatus.RETURNING

    def finish(self, d: Drive) -> None:
        """Home found and returned to: shift the position reference (home point reads as 0x607C)."""
        run = self.run
        gen = self.gen
        home_offset_m = int(d._obj(0x607C)) * d._u
        old_zero = d._zero_m
        d._zero_m = run.home_m - home_offset_m
        shift = d._zero_m - old_zero
        d._demand_m -= shift
        gen.profile.reset(gen.profile.position_m - shift, 0.0)
        gen.jerk.reset(gen.profile.position_m, 1)
        gen.target_m = gen.profile.position_m
        run.status = hm.HomingStatus.ATTAINED
        d._homed = True
        d._notify("homed")

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return self.run is None or self.run.status in (hm.HomingStatus.ATTAINED, hm.HomingStatus.ERROR)

    def status_bits(self, d: Drive) -> int:
        # bits 13/12/10: idle or interrupted 0/0/1 (0/1/1 once homed), in progress 0/0/0, attained 0/1/1,
        # error 1/0/0 (1/0/1 at standstill); returned with 0x8000 = "replace bit 10"
        run = self.run
        if run is None:
            return 0x8000 | (0x1400 if d._homed else 0x400)
        if run.status == hm.HomingStatus.ATTAINED:
            return 0x8000 | 0x1400
        if run.status == hm.HomingStatus.ERROR:
            return 0x8000 | 0x2000 | (0x400 if d._speed_zero_flag() else 0)
        return 0x8000


class CyclicPosition(OperatingMode):
    """CSP (8): 0x607A every cycle, interpolated over 0x60C2 (``interp``), velocity offset 0x60B1 as
    feed-forward."""

    number = CSP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.interp = LinearInterpolator()
        self.interp.reset(gen.target_m)

    def reset(self, d: Drive, p_m: float) -> None:
        self.interp.reset(p_m)

    def enter(self, d: Drive) -> None:
        # the master's next target takes over; until then the demand is the actual position (+ lag)
        moving = d._power and not rx.at_standstill(d)
        v_act = d._axis.velocity_m_s if moving else 0.0
        if moving and d._smode != CONTROL_MODE.POSITION:
            d._demand_m += d._lag_m(v_act)
            self.interp.reset(d._demand_m)
        d._set_sim_mode(CONTROL_MODE.POSITION)
        d.sim.set_position_setpoint(d._demand_m + d._zero_m, v_act, 0.0)

    def on_target_position(self, d: Drive, value: int) -> None:
        if d._state_enabled() and d._stop is None:
            target = d._check_limit(value * d._u, value)
            if target is not None:
                self.interp.new_target(target, d._interp_cycles())

    def cycle(self, d: Drive) -> None:
        p, slope = self.interp.step()
        d._set_position(p, slope / d.cycle_s + int(d.objects[(0x60B1, 0)]) * d._u)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        self.interp.reset(d._demand_m)  # no further targets: hold (a CS mode follows the master)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        x = ax.position_m - d._zero_m
        it = self.interp
        cond = abs(it.end - x) <= pc.position_window_m and it.i >= it.n
        return d._tr_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, d: Drive) -> int:
        # bit 12: the drive follows the command value (not while a shutdown / disable-operation ramp runs)
        return (0x1000 if d._stop is None else 0) | (0x2000 if d._fe_exceeded else 0)


class ProfileVelocity(OperatingMode):
    """PV (3): 0x60FF ramped with 0x6083 / 0x6084 (``vramp``), from the actual speed."""

    number = PV
    control = CONTROL_MODE.VELOCITY

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.vramp = VelocityRamp(gen.profile.dt_s)
        self.interp_v = LinearInterpolator()  # CSV: the cyclic velocity targets

    def enter(self, d: Drive) -> None:
        self.vramp.velocity_m_s = d._axis.velocity_m_s if d._power else 0.0
        self.interp_v = LinearInterpolator()
        self.interp_v.reset(self.vramp.velocity_m_s)
        d._set_sim_mode(CONTROL_MODE.VELOCITY)
        d.sim.set_velocity_setpoint(self.vramp.velocity_m_s)

    def cycle(self, d: Drive) -> None:
        o, u = d.objects, d._u
        requested = int(o[(0x60FF, 0)]) * u
        clamped = d._clamp_velocity(requested)
        target = d._velocity_limit(clamped)
        d._internal_limit = d._internal_limit or clamped != requested
        if d._cw & 0x100:
            decel = self.halt_decel_m_s2(d)
            if math.isinf(decel):
                self.current_halt = "braking"  # speed set-point 0: the speed controller brakes at the limit
            self.stop(d, decel)
            return
        if self.current_halt is not None:  # released: the ramp goes on from the actual speed
            self.vramp.velocity_m_s = d._axis.velocity_m_s
            self.current_halt = None
        v = self.vramp.step(target, float(o[(0x6083, 0)]) * u, float(o[(0x6084, 0)]) * u)
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        v = self.vramp.step(0.0, decel_m_s2, decel_m_s2)
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        target = d._clamp_velocity(int(d.objects[(0x60FF, 0)]) * d._u) if not d._cw & 0x100 else 0.0
        cond = abs(target - ax.velocity_m_s) <= pc.velocity_window_m_s
        return d._tr_timer.update(cond, dt, pc.velocity_time_s)

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._speed_zero_flag() else 0  # bit 12: speed = 0

    def quick_stop_bits(self, d: Drive) -> int:
        return 0x1000 if d._speed_zero_flag() else 0  # speed = 0 tells the actual motion in any state


class CyclicVelocity(ProfileVelocity):
    """CSV (9): 0x60FF + 0x60B1 every cycle, interpolated over 0x60C2 (``interp_v``)."""

    number = CSV

    def enter(self, d: Drive) -> None:
        super().enter(d)
        self.on_target_velocity(d)

    def on_target_velocity(self, d: Drive) -> None:
        if d._state_enabled() and d._stop is None:
            v = (int(d._obj(0x60FF)) + int(d._obj(0x60B1))) * d._u
            self.interp_v.new_target(d._clamp_velocity(v), d._interp_cycles())

    def cycle(self, d: Drive) -> None:
        v, _ = self.interp_v.step()
        v = d._velocity_limit(v)
        o = d.objects
        requested = (int(o[(0x60FF, 0)]) + int(o[(0x60B1, 0)])) * d._u
        d._internal_limit = d._internal_limit or d._clamp_velocity(requested) != requested
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._stop is None else 0  # bit 12: follows the command value (not while stopping)

    def quick_stop_bits(self, d: Drive) -> int:
        return 0  # bit 12 is "follows the command value" here, not PV's "speed = 0"


class ProfileTorque(OperatingMode):
    """PT (4): 0x6071 ramped with 0x6087 (per mille of rated torque per second; 0 = step); ``torque_nm``
    is the ramp's output [N m]."""

    number = PT
    control = CONTROL_MODE.TORQUE

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.torque_nm = 0.0

    def enter(self, d: Drive) -> None:
        # ramps from the torque the motor gives now (bumpless from CST), else from zero
        from_torque = d._power and d._smode == CONTROL_MODE.TORQUE
        self.torque_nm = d._axis.torque_nm if from_torque else 0.0
        d._set_sim_mode(CONTROL_MODE.TORQUE)

    def target_nm(self, d: Drive, rated_nm: float) -> float:
        """Where the ramp goes: 0x6071 limited by 0x6072, zero while halted (CW bit 8) [N m]."""
        if d._cw & 0x100:
            return 0.0
        t_max = float(d._obj(0x6072)) / 1000.0 * rated_nm
        return max(-t_max, min(t_max, int(d._obj(0x6071)) / 1000.0 * rated_nm))

    def cycle(self, d: Drive) -> None:
        rated_nm = float(d._obj(0x6076)) / 1000.0
        target = self.target_nm(d, rated_nm)
        slope = float(d._obj(0x6087)) / 1000.0 * rated_nm * d.cycle_s
        diff = target - self.torque_nm
        self.torque_nm = target if slope <= 0 or abs(diff) <= slope else (
            self.torque_nm + math.copysign(slope, diff))
        requested = int(d._obj(0x6071)) / 1000.0 * rated_nm
        d._apply_torque(self.torque_nm, rated_nm, requested_nm=requested)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        self.torque_nm = 0.0  # (the halt of PT is its ramp to zero torque, handled in cycle)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:  # the ramp has arrived at its target
        return self.torque_nm == self.target_nm(d, d._pc.rated_nm)


class CyclicTorque(ProfileTorque):
    """CST (10): 0x6071 + 0x60B2 every cycle."""

    number = CST

    def cycle(self, d: Drive) -> None:
        o = d.objects
        rated_nm = float(o[(0x6076, 0)]) / 1000.0
        d._apply_torque((int(o[(0x6071, 0)]) + int(o[(0x60B2, 0)])) / 1000.0 * rated_nm, rated_nm)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._stop is None else 0  # bit 12: follows the command value (not while stopping)


MODE_CLASSES: tuple[type[OperatingMode], ...] = (
    OperatingMode, ProfilePosition, ProfileVelocity, ProfileTorque, Homing, CyclicPosition, CyclicVelocity,
    CyclicTorque)


def make_modes(cycle_s: float, position_m: float) -> dict[int, OperatingMode]:
    """A fresh set of mode objects for one drive: 0x6060 value -> mode object (0: no mode), sharing one
    :class:`ProfileGenerator` at rest at ``position_m`` (drive coordinate [m])."""
    gen = ProfileGenerator(cycle_s, position_m)
    return {cls.number: cls(gen) for cls in MODE_CLASSES}

