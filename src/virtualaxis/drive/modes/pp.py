"""PP (1): profile position with the set-point handshake."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import MAX_JERK_FILTER_CYCLES

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class ProfilePosition(OperatingMode):
    """PP (1): trapezoid / jerk-limited profile to 0x607A with the set-point handshake (bits 4, 5, 6) and
    change on set-point (bit 9): with bit 9 = 1 (bit 5 = 0) a buffered set-point that lies further on in the
    direction of travel is started when the profile passes the first target, which it passes at the profile
    velocity of the first set-point (no stop there); a buffered set-point behind the first target waits until
    the first one is reached, as with bit 9 = 0."""

    number = OperationMode.PP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.ack = False  # statusword bit 12 "set-point acknowledge"
        self.pending_m: float | None = None  # buffered set-point (single set-point, not change immediately)
        self.halting = False  # the halt's braking profile is planned (once, when bit 8 rises)
        self.setpoint_velocity = 0  # 0x6081 as the running set-point was taken (its velocity through a target)
        self.unstarted = False  # a set-point taken at rest that no cycle has started yet (it is the running one)

    def reset(self, ctx: ModeContext, p_m: float) -> None:
        super().reset(ctx, p_m)
        self.ack = False
        self.pending_m = None
        self.halting = False
        self.unstarted = False
        self.setpoint_velocity = int(ctx.obj(0x6081))

    def entry_decel_m_s2(self, ctx: ModeContext) -> float:
        return float(ctx.obj(0x6084)) * ctx.u

    def limits(self, ctx: ModeContext, velocity: int | None = None) -> tuple[float, float, float]:
        """Profile velocity (0x6081, or ``velocity`` [pos unit/s], limited by 0x607F and 0x6080), acceleration
        0x6083, deceleration 0x6084 [m/s, m/s^2, m/s^2]."""
        o, u = ctx.objects, ctx.u
        v = min(float(o[(0x6081, 0)] if velocity is None else velocity), float(o[(0x607F, 0)])) * u
        return min(v, ctx.params().max_speed_m_s), float(o[(0x6083, 0)]) * u, float(o[(0x6084, 0)]) * u

    def passing_through(self, ctx: ModeContext) -> bool:
        """Change on set-point (controlword bit 9 = 1, bit 5 = 0): a buffered set-point lies beyond the running
        target in the direction the profile travels to it, so the profile passes that target without stopping."""
        if self.pending_m is None or ctx.cw & 0x220 != 0x200:
            return False
        first = self.gen.target_m
        ahead = first - self.gen.profile.position_m
        return ahead != 0.0 and ahead * (self.pending_m - first) > 0.0

    def cycle(self, ctx: ModeContext) -> None:
        gen = self.gen
        halt = bool(ctx.cw & 0x100)
        through = False
        v, a, dec = self.limits(ctx)
        if halt:
            decel = self.halt_decel_m_s2(ctx)
            if math.isinf(decel) or self.current_halt is not None:
                self.halt_on_current_limit(ctx)
                return
            if not self.halting:  # planned once: re-planned every cycle it braked at about half of 0x6084
                gen.brake(a, decel)
                self.halting = True
        else:
            if self.current_halt is not None:
                self.release_current_halt(ctx)
            self.halting = False
            through = self.passing_through(ctx)
            if through:  # toward the buffered target, at the first set-point's velocity up to the first target
                vt, _, _ = self.limits(ctx, self.setpoint_velocity)
                gen.profile.set_target(self.pending_m, vt, a, dec)
            else:
                gen.profile.set_target(gen.target_m, v, a, dec)
            self.unstarted = False
        p = self._profile_step(ctx)
        if not halt and self.pending_m is not None and (
                (through and (p - gen.target_m) * (self.pending_m - gen.target_m) >= 0.0)
                or (gen.profile.done and gen.jerk.settled(p))):
            gen.target_m = self.pending_m
            self.pending_m = None
            self.setpoint_velocity = int(ctx.obj(0x6081))
            self.start_move(ctx)
            if not ctx.cw & 0x10:
                self.ack = False

    @staticmethod
    def jerk_cycles(ctx: ModeContext) -> int:
        """Length of the jerk filter a set-point gets now [drive cycles]: T_j = 0x6083 / 0x60A4 with 0x6086 = 3,
        else 1 (may exceed :data:`MAX_JERK_FILTER_CYCLES`: such a set-point cannot be planned)."""
        o = ctx.objects
        jerk = float(o[(0x60A4, 1)])
        if int(o[(0x6086, 0)]) != 3 or jerk <= 0:
            return 1
        cycles = float(o[(0x6083, 0)]) / jerk / ctx.cycle_s
        return MAX_JERK_FILTER_CYCLES + 1 if cycles > MAX_JERK_FILTER_CYCLES else max(1, int(round(cycles)))

    def plannable(self, ctx: ModeContext) -> bool:
        """Whether a set-point can be planned with the present profile objects; if not, it is refused
        (``ctx.refuse_setpoint``: warning EMCY, SDO abort) and the axis stays where the profile is."""
        n = self.jerk_cycles(ctx)
        if n <= MAX_JERK_FILTER_CYCLES:
            return True
        acc, jerk = int(ctx.objects[(0x6083, 0)]), int(ctx.objects[(0x60A4, 1)])
        ctx.refuse_setpoint(
            f"set-point not planned: jerk time T_j = 0x6083 / 0x60A4 = {acc} / {jerk} = {acc / jerk:g} s is longer "
            f"than {MAX_JERK_FILTER_CYCLES} drive cycles ({MAX_JERK_FILTER_CYCLES * ctx.cycle_s:g} s)")
        return False

    def start_move(self, ctx: ModeContext) -> None:
        """A new set-point takes effect: the jerk filter length from 0x6086 / 0x60A4 (only when at rest). One
        that cannot be planned (the profile objects changed since it was accepted) is refused: the profile
        stops where it is."""
        gen = self.gen
        pr = gen.profile
        n = self.jerk_cycles(ctx)
        if n > MAX_JERK_FILTER_CYCLES:
            self.plannable(ctx)
            gen.target_m = pr.position_m if pr.done else gen.target_m
            return
        if n > 1 and gen.jerk.settled(pr.position_m) and pr.done:
            gen.jerk.reset(pr.position_m, n)
        elif n == 1 and gen.jerk.n != 1 and gen.jerk.settled(pr.position_m):
            gen.jerk.reset(pr.position_m, 1)

    def controlword(self, ctx: ModeContext, old_cw: int, cw: int) -> None:
        """Set-point handshake: rising bit 4 takes 0x607A (bit 6 relative, bit 5 change immediately)."""
        if cw & 0x10 and not old_cw & 0x10:
            if not self.ack or cw & 0x20:
                value = int(ctx.obj(0x607A)) * ctx.setpoints.position_sign
                base = self.pending_m if self.pending_m is not None else self.gen.target_m
                target = base + value * ctx.u if cw & 0x40 else value * ctx.u
                target_l = ctx.setpoints.check_limit(target, value) if self.plannable(ctx) else None
                if target_l is not None:
                    ctx.accept_setpoint()
                    if cw & 0x20 or (self.gen.settled() and not self.unstarted):
                        # change immediately, or at rest: the running set-point (a second one before the next
                        # cycle is buffered behind it, not put in its place)
                        self.gen.target_m = target_l
                        self.pending_m = None
                        self.setpoint_velocity = int(ctx.obj(0x6081))
                        self.start_move(ctx)
                        self.unstarted = not cw & 0x20
                    else:
                        self.pending_m = target_l
                    self.ack = True
                    ctx.restart_target_window()
        elif not cw & 0x10 and self.pending_m is None:
            self.ack = False

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        pc = ctx.params()
        gen = self.gen
        pr = gen.profile
        if ctx.cw & 0x100 and pr.velocity_m_s == 0.0:  # halted
            return True
        x = ax.position_m - ctx.setpoints.zero_m
        cond = (
            pr.done
            and self.pending_m is None
            and gen.jerk.settled(pr.position_m)
            and abs(gen.target_m - x) <= pc.position_window_m
        )
        return ctx.target_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, ctx: ModeContext) -> int:
        sw = 0x1000 if self.ack else 0
        return sw | (0x2000 if ctx.fe_timer.held_s > 0 and ctx.fe_exceeded else 0)
