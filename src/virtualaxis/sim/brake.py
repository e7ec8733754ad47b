"""The holding brake of an axis: a spring-applied friction brake on the table (``[effects] brake_*`` keys).

Engaged, it holds the table up to its holding force ``brake_holding_force_n`` (the compiled plant adds it to the
table's Coulomb friction: the table sticks while the net force on it stays within the friction plus the
holding force, and slips beyond it, braked by that force). Released, it has no force. The brake does not follow
its command at once: it releases ``brake_opening_time_s`` after the command to open (coil energised) and holds
again ``brake_closing_time_s`` after the command to close (coil de-energised), the times a brake's data sheet
gives (armature travel and field decay). Without a holding force the axis has no brake.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from virtualaxis.config import AxisConfig


@dataclass
class HoldingBrake:
    """A holding brake's physics: its command (``released_commanded``) and, from the command's time, the
    holding force it has at a time [N]."""

    holding_force_n: float
    opening_time_s: float
    closing_time_s: float
    released_commanded: bool = False
    commanded_at_s: float = -math.inf  # plant time of the last command change [s]

    @classmethod
    def of(cls, cfg: AxisConfig) -> HoldingBrake | None:
        """The axis' brake (``None`` without a holding force): engaged, as a brake without power is."""
        e = cfg.effects
        if not e.brake_holding_force_n > 0:
            return None
        return cls(float(e.brake_holding_force_n), float(e.brake_opening_time_s), float(e.brake_closing_time_s))

    def command(self, released: bool, t_s: float) -> None:
        """Energise (``released``) or de-energise the brake's coil at plant time ``t_s``."""
        if released != self.released_commanded:
            # a command reversed before the last one took effect: the brake is still as commanded now
            already = self.is_released(t_s) == released
            self.released_commanded = released
            self.commanded_at_s = -math.inf if already else t_s

    def is_released(self, t_s: float) -> bool:
        """Whether the brake is released (no holding force) at plant time ``t_s``."""
        elapsed = t_s - self.commanded_at_s
        if self.released_commanded:
            return elapsed >= self.opening_time_s - 1e-12
        return elapsed < self.closing_time_s - 1e-12

    def force_n(self, t_s: float) -> float:
        """The holding force the brake has at plant time ``t_s`` [N] (0 while released)."""
        return 0.0 if self.is_released(t_s) else self.holding_force_n
