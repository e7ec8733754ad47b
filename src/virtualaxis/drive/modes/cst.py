"""CST (10): cyclic synchronous torque."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive.modes.base import register
from virtualaxis.drive.modes.pt import ProfileTorque
from virtualaxis.drive.opmodes import OperationMode

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive


@register
class CyclicTorque(ProfileTorque):
    """CST (10): 0x6071 + 0x60B2 every cycle."""

    number = OperationMode.CST

    def cycle(self, d: Drive) -> None:
        o = d.objects
        rated_nm = float(o[(0x6076, 0)]) / 1000.0
        d._apply_torque((int(o[(0x6071, 0)]) + int(o[(0x60B2, 0)])) / 1000.0 * rated_nm, rated_nm)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        return False

    def status_bits(self, d: Drive) -> int:
        return 0x1000 if d._stop is None else 0  # bit 12: follows the command value (not while stopping)
