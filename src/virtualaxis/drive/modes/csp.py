"""CSP (8): cyclic synchronous position."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import LinearInterpolator
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class CyclicPosition(OperatingMode):
    """CSP (8): 0x607A every cycle, interpolated over 0x60C2 (``interp``), velocity offset 0x60B1 as
    feed-forward."""

    number = OperationMode.CSP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.interp = LinearInterpolator()
        self.interp.reset(gen.target_m)

    def reset(self, ctx: ModeContext, p_m: float) -> None:
        self.interp.reset(p_m)

    def enter(self, ctx: ModeContext) -> None:
        # the master's next target takes over; until then the demand is the actual position (+ lag)
        moving = ctx.powered and not rx.at_standstill(ctx)
        v_act = ctx.axis.velocity_m_s if moving else 0.0
        if moving and ctx.setpoints.control != CONTROL_MODE.POSITION:
            ctx.setpoints.demand_m += ctx.lag_m(v_act)
            self.interp.reset(ctx.setpoints.demand_m)
        ctx.setpoints.set_control(CONTROL_MODE.POSITION)
        ctx.setpoints.send_position(ctx.setpoints.demand_m, v_act, 0.0)

    def on_target_position(self, ctx: ModeContext, value: int) -> None:
        if ctx.enabled and not ctx.stopping:
            target = ctx.setpoints.check_limit(value * ctx.u, value)
            if target is not None:
                self.interp.new_target(target, ctx.params().interp_cycles)

    def cycle(self, ctx: ModeContext) -> None:
        p, slope = self.interp.step()
        offset = int(ctx.objects[(0x60B1, 0)]) * ctx.u * ctx.setpoints.position_sign
        ctx.setpoints.position(p, slope / ctx.cycle_s + offset)

    def stop(self, ctx: ModeContext, decel_m_s2: float) -> None:
        self.interp.reset(ctx.setpoints.demand_m)  # no further targets: hold (a CS mode follows the master)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        pc = ctx.params()
        x = ax.position_m - ctx.setpoints.zero_m
        it = self.interp
        cond = abs(it.end - x) <= pc.position_window_m and it.i >= it.n
        return ctx.target_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, ctx: ModeContext) -> int:
        # bit 12: the drive follows the command value (not while a shutdown / disable-operation ramp runs)
        return (0x1000 if not ctx.stopping else 0) | (0x2000 if ctx.fe_exceeded else 0)
