"""PT (4): profile torque."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class ProfileTorque(OperatingMode):
    """PT (4): 0x6071 ramped with 0x6087 (per mille of rated torque per second; 0 = step); ``torque_nm``
    is the ramp's output [N m]."""

    number = OperationMode.PT
    control = CONTROL_MODE.TORQUE

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.torque_nm = 0.0

    def enter(self, ctx: ModeContext) -> None:
        # ramps from the torque the motor gives now (bumpless from CST), else from zero
        from_torque = ctx.powered and ctx.setpoints.control == CONTROL_MODE.TORQUE
        self.torque_nm = ctx.axis.torque_nm if from_torque else 0.0
        ctx.setpoints.set_control(CONTROL_MODE.TORQUE)

    def target_nm(self, ctx: ModeContext, rated_nm: float) -> float:
        """Where the ramp goes: 0x6071 limited by 0x6072, zero while halted (CW bit 8) [N m]."""
        if ctx.cw & 0x100:
            return 0.0
        t_max = float(ctx.obj(0x6072)) / 1000.0 * rated_nm
        return max(-t_max, min(t_max, int(ctx.obj(0x6071)) / 1000.0 * rated_nm * ctx.setpoints.velocity_sign))

    def cycle(self, ctx: ModeContext) -> None:
        rated_nm = float(ctx.obj(0x6076)) / 1000.0
        target = self.target_nm(ctx, rated_nm)
        slope = float(ctx.obj(0x6087)) / 1000.0 * rated_nm * ctx.cycle_s
        diff = target - self.torque_nm
        self.torque_nm = target if slope <= 0 or abs(diff) <= slope else (
            self.torque_nm + math.copysign(slope, diff))
        requested = int(ctx.obj(0x6071)) / 1000.0 * rated_nm * ctx.setpoints.velocity_sign
        t_max = float(ctx.obj(0x6072)) / 1000.0 * rated_nm
        ctx.setpoints.torque(self.torque_nm, rated_nm, t_max, requested_nm=requested)

    def stop(self, ctx: ModeContext, decel_m_s2: float) -> None:
        self.torque_nm = 0.0  # (the halt of PT is its ramp to zero torque, handled in cycle)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:  # the ramp has arrived at its target
        return self.torque_nm == self.target_nm(ctx, ctx.params().rated_nm)
