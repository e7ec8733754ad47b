"""CST (10): cyclic synchronous torque."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import register
from virtualaxis.drive.modes.pt import ProfileTorque
from virtualaxis.drive.opmodes import OperationMode

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext


@register
class CyclicTorque(ProfileTorque):
    """CST (10): 0x6071 + 0x60B2 every cycle."""

    number = OperationMode.CST

    def cycle(self, ctx: ModeContext) -> None:
        o = ctx.objects
        rated_nm = float(o[(0x6076, 0)]) / 1000.0
        t_max = float(o[(0x6072, 0)]) / 1000.0 * rated_nm
        sign = ctx.setpoints.velocity_sign
        ctx.setpoints.torque((int(o[(0x6071, 0)]) + int(o[(0x60B2, 0)])) / 1000.0 * rated_nm * sign, rated_nm, t_max)

    def target_reached(self, ctx: ModeContext, ax, dt: float) -> bool:
        return False

    def status_bits(self, ctx: ModeContext) -> int:
        return 0x1000 if not ctx.stopping else 0  # bit 12: follows the command value (not while stopping)
