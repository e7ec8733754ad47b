"""PV (3): profile velocity."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import LinearInterpolator, VelocityRamp
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class ProfileVelocity(OperatingMode):
    """PV (3): 0x60FF ramped with 0x6083 / 0x6084 (``vramp``), from the actual speed."""

    number = OperationMode.PV
    control = CONTROL_MODE.VELOCITY

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.vramp = VelocityRamp(gen.profile.dt_s)
        self.interp_v = LinearInterpolator()  # CSV: the cyclic velocity targets

    def enter(self, ctx: ModeContext) -> None:
        self.vramp.velocity_m_s = ctx.axis.velocity_m_s if ctx.powered else 0.0
        self.interp_v = LinearInterpolator()
        self.interp_v.reset(self.vramp.velocity_m_s)
        ctx.setpoints.set_control(CONTROL_MODE.VELOCITY)
        ctx.setpoints.send_velocity(self.vramp.velocity_m_s)

    def cycle(self, ctx: ModeContext) -> None:
        o, u = ctx.objects, ctx.u
        requested = int(o[(0x60FF, 0)]) * u * ctx.setpoints.velocity_sign
        clamped = ctx.setpoints.clamp_velocity(requested)
        target = ctx.setpoints.velocity_limit(clamped)
        if clamped != requested:
            ctx.setpoints.internal_limit = True
        if ctx.cw & 0x100:
            decel = self.halt_decel_m_s2(ctx)
            if math.isinf(decel):
                self.current_halt = "braking"  # speed set-point 0: the speed controller brakes at the limit
            self.stop(ctx, decel)
            return
        if self.current_halt is not None:  # released: the ramp goes on from the actual speed
            self.vramp.velocity_m_s = ctx.axis.velocity_m_s
            self.current_halt = None
        v = self.vramp.step(target, float(o[(0x6083, 0)]) * u, float(o[(0x6084, 0)]) * u)
        ctx.setpoints.demand_v = v
        ctx.setpoints.send_velocity(v)

    def stop(self, ctx: ModeContext, decel_m_s2: float) -> None:
        v = self.vramp.step(0.0, decel_m_s2, decel_m_s2)
        ctx.setpoints.demand_v = v
        ctx.setpoints.send_velocity(v)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        pc = ctx.params()
        target = (ctx.setpoints.clamp_velocity(int(ctx.objects[(0x60FF, 0)]) * ctx.u * ctx.setpoints.velocity_sign)
                  if not ctx.cw & 0x100 else 0.0)
        cond = abs(target - ax.velocity_m_s) <= pc.velocity_window_m_s
        return ctx.target_timer.update(cond, dt, pc.velocity_time_s)

    def status_bits(self, ctx: ModeContext) -> int:
        return 0x1000 if ctx.speed_zero else 0  # bit 12: speed = 0

    def quick_stop_bits(self, ctx: ModeContext) -> int:
        return 0x1000 if ctx.speed_zero else 0  # speed = 0 tells the actual motion in any state
