"""Position factor (0x608F, 0x6091, 0x6092): user position units and increments <-> table metres.

CiA 402 position factor: one revolution of the driving shaft (the ball screw) moves the table by
``lead_m`` and by ``feed`` position units (0x6092:1 per 0x6092:2 shaft revolutions), so

    metres per position unit = lead_m * 0x6092:2 / 0x6092:1

Increments (0x6063) count encoder increments of the motor: 0x608F:1 per 0x608F:2 motor revolutions,
with 0x6091:1 motor revolutions per 0x6091:2 shaft revolutions. Velocities are position units per
second, accelerations position units per s^2, jerk per s^3.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PositionScaling:
    """Conversion factors between the OD's integer units and SI (metres at the table)."""

    lead_m: float  # table travel per driving-shaft revolution
    feed_units: int  # 0x6092:1
    feed_shaft_revs: int  # 0x6092:2
    encoder_increments: int  # 0x608F:1
    encoder_motor_revs: int  # 0x608F:2
    gear_motor_revs: int  # 0x6091:1
    gear_shaft_revs: int  # 0x6091:2

    @property
    def metres_per_unit(self) -> float:
        return self.lead_m * self.feed_shaft_revs / self.feed_units

    @property
    def motor_rev_travel_m(self) -> float:
        """Table travel per motor revolution [m]: the lead through the gear 0x6091 (one index pulse, 0x608F
        increments and one revolution of 0x6080 each)."""
        return self.lead_m * self.gear_shaft_revs / self.gear_motor_revs

    @property
    def increments_per_metre(self) -> float:
        inc_per_motor_rev = self.encoder_increments / self.encoder_motor_revs
        return inc_per_motor_rev / self.motor_rev_travel_m

    def to_units(self, metres: float) -> int:
        """Metres (or m/s, m/s^2) -> nearest integer user units (saturation is the caller's job)."""
        return int(round(metres / self.metres_per_unit))

    def to_metres(self, units: float) -> float:
        return float(units) * self.metres_per_unit

    def to_increments(self, metres: float) -> int:
        return int(round(metres * self.increments_per_metre))

    @staticmethod
    def valid(values: dict[tuple[int, int], int]) -> str:
        """'' if the factor objects in ``values`` are usable, else why not."""
        for key in ((0x6092, 1), (0x6092, 2), (0x608F, 1), (0x608F, 2), (0x6091, 1), (0x6091, 2)):
            if values.get(key, 1) <= 0:
                return f"0x{key[0]:04X}:{key[1]} must be > 0"
        return ""
