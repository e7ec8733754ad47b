"""The CiA 402 modes of operation, one object each, with one small contract (:class:`OperatingMode`):

- ``enter(drive)``: take over the axis FROM ITS ACTUAL MOTION (a mode change while moving decelerates with
  the new mode's own deceleration; velocity and torque modes start from the actual speed / torque);
- ``cycle(drive)``: one position-loop cycle: the mode's set-point to the plant (position + feed-forward,
  speed or torque);
- ``stop(drive, decel_m_s2)``: ramp to rest with the given deceleration (halt, controlword bit 8);
- ``target_reached(drive, ax, dt)`` and ``status_bits(drive)``: statusword bits 10 / 12 / 13.

The drive (``virtualaxis.drive.core.Drive``) owns the state those objects act on (set-point generators,
the PP set-point handshake, the homing run); the objects hold no state of their own, so the drive's
power-on reset resets everything. Stops for faults / quick stop / limit switches are not the mode's: they
run in :mod:`virtualaxis.drive.reactions`, from the actual speed, whatever the mode.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive import homing as hm
from virtualaxis.drive import reactions as rx
from virtualaxis.drive.profiles import LinearInterpolator
from virtualaxis.sim import ControlMode

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive

PP, PV, PT, HM, CSP, CSV, CST = 1, 3, 4, 6, 8, 9, 10


class OperatingMode:
    """Common contract; the base class is "no mode" (0x6060 = 0): hold the position."""

    number = 0
    control = ControlMode.POSITION

    # ------------------------------------------------------------------ enter
    def enter(self, d: Drive) -> None:
        """Take over from the actual motion: in position control, a moving axis decelerates with
        :meth:`entry_decel_m_s2` to rest from where it is (no hard stop), else hold the demand."""
        ax = d._axis
        v_act = ax.velocity_m_s if d._power else 0.0
        if not rx.at_standstill(d):
            p = ax.position_m - d._zero_m + d._lag_m(v_act)  # bumpless: speed set-point = actual speed
            decel = max(self.entry_decel_m_s2(d), 1e-6)
            stop_at = p + v_act * abs(v_act) / (2.0 * decel)
            d._demand_m = p
            d._profile.reset(p, v_act)
            d._profile.set_target(stop_at, max(abs(v_act), 1e-9), decel, decel)
            d._jerk.reset(p, 1)
            d._pp_target_m = stop_at
            d._last_vff = v_act
            d._set_sim_mode(ControlMode.POSITION)
            d.sim.set_position_setpoint(p + d._zero_m, v_act, 0.0)
            return
        d._set_sim_mode(ControlMode.POSITION)
        d.sim.set_position_setpoint(d._demand_m + d._zero_m, 0.0, 0.0)

    def entry_decel_m_s2(self, d: Drive) -> float:
        """Deceleration of a stop when the mode is entered while moving [m/s^2] (no mode: 0x6085)."""
        return float(d._obj(0x6085)) * d._u

    # ------------------------------------------------------------------ cycle
    def cycle(self, d: Drive) -> None:
        if d._profile.velocity_m_s == 0.0:  # hold (after a stop from motion, see enter)
            d._profile.set_target(d._profile.position_m, 1.0, 1.0, 1.0)
        self._profile_step(d)

    def _profile_step(self, d: Drive) -> float:
        """Step the position profile (+ jerk filter) and send it to the position loop; returns the position."""
        p, _ = d._profile.step()
        pf = d._jerk.step(p)
        d._set_position(pf, (pf - d._demand_m) / d.cycle_s)
        return p

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        """Ramp the position profile to rest with ``decel_m_s2``."""
        pv = d._profile.velocity_m_s
        stop_at = d._profile.position_m + pv * abs(pv) / (2 * decel_m_s2)
        d._profile.set_target(stop_at, max(abs(pv), 1e-9), max(d._profile.a_max, 1e-9), decel_m_s2)

    # ------------------------------------------------------------------ status
    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        """Bits 12 / 13 (and 10 where the mode redefines it) in OPERATION ENABLED."""
        return 0


class ProfilePosition(OperatingMode):
    """PP (1): trapezoid / jerk-limited profile to 0x607A with the set-point handshake (bits 4, 5, 6)."""

    number = PP

    def entry_decel_m_s2(self, d: Drive) -> float:
        return float(d._obj(0x6084)) * d._u

    def cycle(self, d: Drive) -> None:
        halt = bool(d._cw & 0x100)
        v, a, dec = d._pp_limits()
        if halt:
            dh = d._halt_decel()
            pv = d._profile.velocity_m_s
            d._profile.set_target(d._profile.position_m + pv * abs(pv) / (2 * dh), max(abs(pv), 1e-9), a, dh)
        else:
            d._profile.set_target(d._pp_target_m, v, a, dec)
        p = self._profile_step(d)
        if not halt and d._pp_pending is not None and d._profile.done and d._jerk.settled(p):
            d._pp_target_m = d._pp_pending
            d._pp_pending = None
            d._start_pp_move()
            if not d._cw & 0x10:
                d._pp_ack = False

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        if d._cw & 0x100 and d._profile.velocity_m_s == 0.0:  # halted
            return True
        x = ax.position_m - d._zero_m
        cond = (
            d._profile.done
            and d._pp_pending is None
            and d._jerk.settled(d._profile.position_m)
            and abs(d._pp_target_m - x) <= pc.position_window_m
        )
        return d._tr_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, d: Drive) -> int:
        sw = 0x1000 if d._pp_ack else 0
        return sw | (0x2000 if d._fe_timer.held_s > 0 and d._fe_exceeded else 0)


class Homing(OperatingMode):
    """HM (6): the methods of :mod:`virtualaxis.drive.homing` on the simulated switches."""

    number = HM

    def entry_decel_m_s2(self, d: Drive) -> float:
        return d._homing_accel()

    def cycle(self, d: Drive) -> None:
        d._run_homing(bool(d._cw & 0x100))
        self._profile_step(d)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return d._homing is None or d._homing.status in (hm.HomingStatus.ATTAINED, hm.HomingStatus.ERROR)

    def status_bits(self, d: Drive) -> int:
        # bits 13/12/10: idle or interrupted 0/0/1 (0/1/1 once homed), in progress 0/0/0, attained 0/1/1,
        # error 1/0/0 (1/0/1 at standstill); returned with 0x8000 = "replace bit 10"
        run = d._homing
        if run is None:
            return 0x8000 | (0x1400 if d._homed else 0x400)
        if run.status == hm.HomingStatus.ATTAINED:
            return 0x8000 | 0x1400
        if run.status == hm.HomingStatus.ERROR:
            return 0x8000 | 0x2000 | (0x400 if abs(d._axis.velocity_m_s) < 1e-4 else 0)
        return 0x8000


class CyclicPosition(OperatingMode):
    """CSP (8): 0x607A every cycle, interpolated over 0x60C2, velocity offset 0x60B1 as feed-forward."""

    number = CSP

    def enter(self, d: Drive) -> None:
        # the master's next target takes over; until then the demand is the actual position (+ lag)
        moving = d._power and not rx.at_standstill(d)
        v_act = d._axis.velocity_m_s if moving else 0.0
        if moving and d._smode != ControlMode.POSITION:
            d._demand_m += d._lag_m(v_act)
            d._interp.reset(d._demand_m)
        d._set_sim_mode(ControlMode.POSITION)
        d.sim.set_position_setpoint(d._demand_m + d._zero_m, v_act, 0.0)

    def cycle(self, d: Drive) -> None:
        p, slope = d._interp.step()
        d._set_position(p, slope / d.cycle_s + int(d._obj(0x60B1)) * d._u)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        d._interp.reset(d._demand_m)  # no further targets: hold (a CS mode follows the master)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        x = ax.position_m - d._zero_m
        cond = abs(d._interp.end - x) <= pc.position_window_m and d._interp.i >= d._interp.n
        return d._tr_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, d: Drive) -> int:
        return 0x1000 | (0x2000 if d._fe_exceeded else 0)  # bit 12: drive follows the command value


class ProfileVelocity(OperatingMode):
    """PV (3): 0x60FF ramped with 0x6083 / 0x6084, from the actual speed."""

    number = PV
    control = ControlMode.VELOCITY

    def enter(self, d: Drive) -> None:
        d._vramp.velocity_m_s = d._axis.velocity_m_s if d._power else 0.0
        d._interp_v = LinearInterpolator()
        d._interp_v.reset(d._vramp.velocity_m_s)
        d._set_sim_mode(ControlMode.VELOCITY)
        d.sim.set_velocity_setpoint(d._vramp.velocity_m_s)

    def cycle(self, d: Drive) -> None:
        requested = int(d._obj(0x60FF)) * d._u
        clamped = d._clamp_velocity(requested)
        target = d._velocity_limit(clamped)
        d._internal_limit = d._internal_limit or clamped != requested
        if d._cw & 0x100:
            self.stop(d, d._halt_decel())
            return
        v = d._vramp.step(target, float(d._obj(0x6083)) * d._u, float(d._obj(0x6084)) * d._u)
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        v = d._vramp.step(0.0, decel_m_s2, decel_m_s2)
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        target = d._clamp_velocity(int(d.objects[(0x60FF, 0)]) * d._u) if not d._cw & 0x100 else 0.0
        cond = abs(target - ax.velocity_m_s) <= pc.velocity_window_m_s
        return d._tr_timer.update(cond, dt, pc.velocity_time_s)

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._speed_zero_flag() else 0  # bit 12: speed = 0


class CyclicVelocity(ProfileVelocity):
    """CSV (9): 0x60FF + 0x60B1 every cycle, interpolated over 0x60C2."""

    number = CSV

    def enter(self, d: Drive) -> None:
        super().enter(d)
        d._on_target_velocity()

    def cycle(self, d: Drive) -> None:
        v, _ = d._interp_v.step()
        v = d._velocity_limit(v)
        requested = (int(d._obj(0x60FF)) + int(d._obj(0x60B1))) * d._u
        d._internal_limit = d._internal_limit or d._clamp_velocity(requested) != requested
        d._demand_v = v
        d.sim.set_velocity_setpoint(v)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000


class ProfileTorque(OperatingMode):
    """PT (4): 0x6071 ramped with 0x6087 (per mille of rated torque per second; 0 = step)."""

    number = PT
    control = ControlMode.TORQUE

    def enter(self, d: Drive) -> None:
        # ramps from the torque the motor gives now (bumpless from CST), else from zero
        from_torque = d._power and d._smode == ControlMode.TORQUE
        d._torque_demand_nm = d._axis.torque_nm if from_torque else 0.0
        d._set_sim_mode(ControlMode.TORQUE)

    def cycle(self, d: Drive) -> None:
        rated_nm = float(d._obj(0x6076)) / 1000.0
        target = d._pt_target_nm(rated_nm)
        slope = float(d._obj(0x6087)) / 1000.0 * rated_nm * d.cycle_s
        diff = target - d._torque_demand_nm
        d._torque_demand_nm = target if slope <= 0 or abs(diff) <= slope else (
            d._torque_demand_nm + math.copysign(slope, diff))
        requested = int(d._obj(0x6071)) / 1000.0 * rated_nm
        d._apply_torque(d._torque_demand_nm, rated_nm, requested_nm=requested)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        d._torque_demand_nm = 0.0  # (the halt of PT is its ramp to zero torque, handled in cycle)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:  # the ramp has arrived at its target
        return d._torque_demand_nm == d._pt_target_nm(d._pc.rated_nm)


class CyclicTorque(ProfileTorque):
    """CST (10): 0x6071 + 0x60B2 every cycle."""

    number = CST

    def cycle(self, d: Drive) -> None:
        rated_nm = float(d._obj(0x6076)) / 1000.0
        d._apply_torque((int(d._obj(0x6071)) + int(d._obj(0x60B2))) / 1000.0 * rated_nm, rated_nm)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000


#: 0x6060 value -> mode object (0: no mode)
MODES: dict[int, OperatingMode] = {
    m.number: m
    for m in (OperatingMode(), ProfilePosition(), ProfileVelocity(), ProfileTorque(), Homing(),
              CyclicPosition(), CyclicVelocity(), CyclicTorque())
}


def mode_object(number: int) -> OperatingMode:
    return MODES.get(number, MODES[0])
