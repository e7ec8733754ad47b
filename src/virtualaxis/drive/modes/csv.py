"""CSV (9): cyclic synchronous velocity."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import register
from virtualaxis.drive.modes.pv import ProfileVelocity
from virtualaxis.drive.opmodes import OperationMode

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive


@register
class CyclicVelocity(ProfileVelocity):
    """CSV (9): 0x60FF + 0x60B1 every cycle, interpolated over 0x60C2 (``interp_v``)."""

    number = OperationMode.CSV

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
        if d._clamp_velocity(requested) != requested:
            d.note_internal_limit()
        d.setpoints.demand_v = v
        d.setpoints.send_velocity(v)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._stop is None else 0  # bit 12: follows the command value (not while stopping)

    def quick_stop_bits(self, d: Drive) -> int:
        return 0  # bit 12 is "follows the command value" here, not PV's "speed = 0"
