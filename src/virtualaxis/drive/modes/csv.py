"""CSV (9): cyclic synchronous velocity."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import register
from virtualaxis.drive.modes.pv import ProfileVelocity
from virtualaxis.drive.opmodes import OperationMode

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class CyclicVelocity(ProfileVelocity):
    """CSV (9): 0x60FF + 0x60B1 every cycle, interpolated over 0x60C2 (``interp_v``)."""

    number = OperationMode.CSV

    def enter(self, ctx: ModeContext) -> None:
        super().enter(ctx)
        self.on_target_velocity(ctx)

    def on_target_velocity(self, ctx: ModeContext) -> None:
        if ctx.enabled and not ctx.stopping:
            v = (int(ctx.obj(0x60FF)) + int(ctx.obj(0x60B1))) * ctx.u * ctx.setpoints.velocity_sign
            self.interp_v.new_target(ctx.setpoints.clamp_velocity(v), ctx.params().interp_cycles)

    def cycle(self, ctx: ModeContext) -> None:
        v, _ = self.interp_v.step()
        v = ctx.setpoints.velocity_limit(v)
        o = ctx.objects
        requested = (int(o[(0x60FF, 0)]) + int(o[(0x60B1, 0)])) * ctx.u * ctx.setpoints.velocity_sign
        if ctx.setpoints.clamp_velocity(requested) != requested:
            ctx.setpoints.internal_limit = True
        ctx.setpoints.demand_v = v
        ctx.setpoints.send_velocity(v)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        return False

    def status_bits(self, ctx: ModeContext) -> int:
        return 0x1000 if not ctx.stopping else 0  # bit 12: follows the command value (not while stopping)

    def quick_stop_bits(self, ctx: ModeContext) -> int:
        return 0  # bit 12 is "follows the command value" here, not PV's "speed = 0"
