"""HM (6): homing on the simulated switches and index pulse (methods in :mod:`virtualaxis.drive.homing`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive import homing as hm
from virtualaxis.drive import reactions as rx
from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


_ACTIVE_HOMING = (hm.HomingStatus.IN_PROGRESS, hm.HomingStatus.RETURNING)
#: homing: the last stretch before a switch edge is crossed at the zero search speed 0x6099:2 [m] (chosen: 2 mm,
#: the edge is latched at that speed as on a drive that creeps over the cam)
HOMING_CRAWL_M = 0.002


@register
class Homing(OperatingMode):
    """HM (6): the methods of :mod:`virtualaxis.drive.homing` on the simulated switches; ``run`` is the
    homing run in progress / last finished (None: idle or interrupted)."""

    number = OperationMode.HM
    status_mask = 0x3400  # homing redefines bit 10 too

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.run: hm.HomingRun | None = None
        self.homed = False  # a homing run has attained the home point since power-on (bit 12 while idle)

    def reset(self, ctx: ModeContext, p_m: float) -> None:
        super().reset(ctx, p_m)
        self.run = None

    def in_progress(self) -> bool:
        return self.run is not None and self.run.status in _ACTIVE_HOMING

    def stopping_after_error(self, ctx: ModeContext) -> bool:
        """A homing run ended in a homing error (an unexpected limit switch) and the axis still brakes (its
        profile, or the actual motion behind it)."""
        return (self.run is not None and self.run.status == hm.HomingStatus.ERROR
                and (self.gen.profile.velocity_m_s != 0.0 or not rx.at_standstill(ctx)))

    @staticmethod
    def accel_m_s2(ctx: ModeContext) -> float:
        """Homing acceleration 0x609A [m/s^2]."""
        return max(float(ctx.obj(0x609A)) * ctx.u, 1e-6)

    def entry_decel_m_s2(self, ctx: ModeContext) -> float:
        return self.accel_m_s2(ctx)

    def slow_down_m_s2(self, ctx: ModeContext) -> float:
        """Halt option 1 in homing: the homing acceleration 0x609A."""
        return self.accel_m_s2(ctx)

    def controlword(self, ctx: ModeContext, old_cw: int, cw: int) -> None:
        """Rising bit 4 starts homing; bit 4 dropped while homing interrupts it (decelerating)."""
        if cw & 0x10 and not old_cw & 0x10:
            self.start(ctx)
        elif not cw & 0x10 and self.in_progress():
            self.run = None  # bit 4 dropped: homing interrupted
            pr = self.gen.profile
            pr.set_target(pr.position_m, 1, 1, self.accel_m_s2(ctx))

    def start(self, ctx: ModeContext) -> None:
        method = int(ctx.obj(0x6098))
        x = ctx.axis.position_m
        neg, pos, home = ctx.switches(x, method)
        phases = hm.method_phases(method, neg, pos, home)
        if phases is None:
            self.run = hm.HomingRun(method, [], x, status=hm.HomingStatus.ERROR, error="unsupported method")
            return
        self.run = hm.HomingRun(method, phases, x)
        self.homed = False
        self.gen.profile.reset(ctx.setpoints.demand_m, 0.0)
        self.gen.jerk.reset(ctx.setpoints.demand_m, 1)
        if not phases:
            self.run.home_m = x
            self.finish(ctx)

    def cycle(self, ctx: ModeContext) -> None:
        halt = bool(ctx.cw & 0x100)
        if halt and (self.current_halt is not None
                     or (self.in_progress() and math.isinf(self.halt_decel_m_s2(ctx)))):
            self.run = None  # halted: homing interrupted
            self.halt_on_current_limit(ctx)
            return
        if not halt and self.current_halt is not None:
            self.release_current_halt(ctx)
        self._phase_step(ctx, halt)
        self._profile_step(ctx)

    def _phase_step(self, ctx: ModeContext, halt: bool) -> None:
        """One cycle of the homing phases: the profile's target for this cycle, switch / index detection."""
        run = self.run
        pr = self.gen.profile
        acc = self.accel_m_s2(ctx)
        if run is None or run.status in (hm.HomingStatus.ATTAINED, hm.HomingStatus.ERROR):
            pr.set_target(pr.position_m if pr.velocity_m_s == 0 else pr.target_m, 1.0, acc, acc)
            return
        if halt:
            self.gen.brake(acc, self.halt_decel_m_s2(ctx))  # 0x605D: 1 homing acceleration, 2 quick-stop ramp
            self.run = None  # halted: interrupted
            return
        x_plant = ctx.axis.position_m
        if run.status == hm.HomingStatus.RETURNING:
            pr.set_target(run.home_m - ctx.setpoints.zero_m, ctx.objects[(0x6099, 2)] * ctx.u, acc, acc)
            if pr.done and abs(ctx.axis.velocity_m_s) < 1e-4:
                self.finish(ctx)
            return
        phase = run.phase
        fast = float(ctx.obj(0x6099, 1)) * ctx.u
        slow = float(ctx.obj(0x6099, 2)) * ctx.u
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
        far = phase.direction * 10.0 * max(ctx.stroke_m, 0.1)
        neg, pos, home = ctx.switches(x_plant, run.method)
        if (neg and pr.velocity_m_s < 0) or (pos and pr.velocity_m_s > 0):
            # on a hardware limit switch and still moving into it (methods 1, 2, 17, 18 search for it): brake at
            # least with the quick-stop deceleration 0x6085, the drive's limit-switch reaction in every mode; a
            # homing acceleration made for the slow return would run the table into the end stop
            acc = max(acc, float(ctx.obj(0x6085)) * ctx.u)
        pr.set_target(pr.position_m + far, speed, acc, acc)
        hit = False
        latched = x_plant
        if phase.signal == "index":
            period = ctx.motor_rev_travel_m
            crossing = hm.index_crossed(ctx.prev_position_m, x_plant, ctx.index_pulse_offset_m, period)
            if crossing is not None and (crossing - ctx.prev_position_m) * phase.direction > 0:
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

    def finish(self, ctx: ModeContext) -> None:
        """Home found and returned to: shift the position reference (home point reads as 0x607C)."""
        run = self.run
        gen = self.gen
        home_offset_m = ctx.home_offset_m()
        old_zero = ctx.setpoints.zero_m
        ctx.setpoints.zero_m = run.home_m - home_offset_m
        shift = ctx.setpoints.zero_m - old_zero
        ctx.setpoints.demand_m -= shift
        gen.profile.reset(gen.profile.position_m - shift, 0.0)
        gen.jerk.reset(gen.profile.position_m, 1)
        gen.target_m = gen.profile.position_m
        run.status = hm.HomingStatus.ATTAINED
        self.homed = True
        ctx.homed()

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        return self.run is None or self.run.status in (hm.HomingStatus.ATTAINED, hm.HomingStatus.ERROR)

    def status_bits(self, ctx: ModeContext) -> int:
        """Bits 13/12/10 (:attr:`status_mask`): idle or interrupted 0/0/1 (0/1/1 once homed), in progress
        0/0/0, attained 0/1/1, error 1/0/0 (1/0/1 at standstill: speed 0 as 0x606F / 0x6070 tell)."""
        run = self.run
        if run is None:
            return 0x1400 if self.homed else 0x400
        if run.status == hm.HomingStatus.ATTAINED:
            return 0x1400
        if run.status == hm.HomingStatus.ERROR:
            return 0x2000 | (0x400 if ctx.speed_zero else 0)
        return 0
