"""IP (7): interpolated position: linear interpolation between the master's set-points 0x60C1:1."""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import LinearInterpolator

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext

#: set-points 0x60C1:1 the drive buffers beyond the segment it interpolates (a further one is refused)
IP_BUFFER_RECORDS = 16


@register
class InterpolatedPosition(OperatingMode):
    """IP (7), sub-mode 0x60C0 = 0 (linear): with controlword bit 4 (enable ip mode) every set-point written to
    0x60C1:1 (normally by a synchronous RPDO, one per SYNC) is the end of a straight segment of one
    interpolation period 0x60C2 from the end of the previous one. Set-points that arrive while a segment runs
    wait in a first-in-first-out buffer of :data:`IP_BUFFER_RECORDS`; one more is refused (warning EMCY 0x6320,
    SDO abort), and the next record taken clears that warning. A record written in the same RPDO as the
    controlword that sets bit 4 is the first point (the drive reacts to the controlword before the record).
    Bit 4 cleared: the buffer is dropped, the running segment completes and the axis holds its end.
    Halt (bit 8): the buffer is dropped and the axis brakes per 0x605D; released, it holds until the next
    set-point. Statusword bit 12 "ip mode active" (bit 4 taken in OPERATION ENABLED), bit 10 target reached
    (the last segment's end within 0x6067 for 0x6068; halted: at rest), bit 13 following error."""

    number = OperationMode.IP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.interp = LinearInterpolator()
        self.interp.reset(gen.target_m)
        self.buffer: deque[float] = deque()
        self.active = False  # bit 4 taken: set-points are interpolated
        self.halting = False  # a halt's braking profile runs (the profile generator drives the axis)

    def reset(self, ctx: ModeContext, p_m: float) -> None:
        super().reset(ctx, p_m)
        self.interp.reset(p_m)
        self.buffer.clear()
        self.active = False
        self.halting = False

    def enter(self, ctx: ModeContext) -> None:
        super().enter(ctx)  # from the actual motion: a moving axis decelerates (0x6085) to rest first
        self.interp.reset(self.gen.target_m)
        self.halting = not rx.at_standstill(ctx)  # (the profile generator brakes it; then the interpolator holds)
        self.active = bool(ctx.cw & 0x10) and not ctx.halted

    def controlword(self, ctx: ModeContext, old_cw: int, cw: int) -> None:
        active = bool(cw & 0x10)
        if active and not self.active and not self.halting:
            self.interp.reset(self.interp.end if self.interp.i >= self.interp.n else self.interp.current())
        if not active:
            self.buffer.clear()
        self.active = active
        if cw & 0x100 and not old_cw & 0x100:  # halt: brake from the interpolated motion
            self.buffer.clear()
            gen = self.gen
            v = ctx.setpoints.demand_v
            gen.profile.reset(ctx.setpoints.demand_m, v)
            gen.jerk.reset(ctx.setpoints.demand_m, 1)
            decel = self.halt_decel_m_s2(ctx)
            decel = float(ctx.obj(0x6085)) * ctx.u if math.isinf(decel) else decel  # (current limit: quick ramp)
            gen.brake(max(decel, 1e-6), max(decel, 1e-6))
            gen.target_m = gen.profile.target_m
            self.halting = True

    def on_interpolation_data(self, ctx: ModeContext, value: int) -> None:
        if not (ctx.enabled and self.active and not ctx.stopping and not ctx.halted):
            return  # (ignored, as CiA 402 has it, until ip mode is enabled)
        target = ctx.setpoints.check_limit(value * ctx.u, value)
        if target is None:
            return
        it = self.interp
        if it.i >= it.n and not self.buffer and not self.halting:
            it.new_target(target, ctx.params().interp_cycles)
        elif len(self.buffer) < IP_BUFFER_RECORDS:
            self.buffer.append(target)
        else:
            ctx.refuse_setpoint(f"interpolation data record 0x60C1:1 = {value} refused: the buffer of "
                                f"{IP_BUFFER_RECORDS} set-points is full")
            return
        ctx.accept_setpoint()  # (clears the warning of a record refused before)

    def cycle(self, ctx: ModeContext) -> None:
        if self.halting:
            p = self._profile_step(ctx)
            if self.gen.settled() and not ctx.halted:
                self.halting = False
                self.interp.reset(p)
            return
        it = self.interp
        if it.i >= it.n and self.buffer:
            it.new_target(self.buffer.popleft(), ctx.params().interp_cycles)
        p, slope = it.step()
        ctx.setpoints.position(p, slope / ctx.cycle_s)

    def stop(self, ctx: ModeContext, decel_m_s2: float) -> None:
        self.buffer.clear()
        self.interp.reset(ctx.setpoints.demand_m)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        pc = ctx.params()
        if self.halting or ctx.halted:
            return ctx.halted and self.gen.settled() and rx.at_standstill(ctx)  # halted: the axis at rest
        x = ax.position_m - ctx.setpoints.zero_m
        it = self.interp
        cond = it.i >= it.n and not self.buffer and abs(it.end - x) <= pc.position_window_m
        return ctx.target_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, ctx: ModeContext) -> int:
        active = self.active and not ctx.stopping and not ctx.halted
        return (0x1000 if active else 0) | (0x2000 if ctx.fe_exceeded else 0)
