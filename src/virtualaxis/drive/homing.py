"""Homing mode (0x6098 methods 1, 2, 17, 18, 19-22, 35, 37) on simulated switches and index pulse.

Simulated inputs (0x60FD): negative / positive limit switch active within ``limit_switch_inset_m`` of
-stroke/2 / +stroke/2; home switch active for x >= ``home_switch_position_m`` (methods 19/20, "positive
home switch"); for methods 21/22 ("negative home switch") the simulated switch is mounted the other way
round, active for x <= ``home_switch_position_m``. The index pulse comes once per motor revolution, at
table positions ``index_pulse_offset_m + k * lead / gear``; its position is latched exactly (like a
hardware probe), switch edges are latched at the cycle they are seen.

A method is a list of phases (direction, speed, stop condition). The final phase's latched position is
the home point; the axis then returns to it at zero-search speed, and the drive shifts its position
reference so that 0x6064 reads the home offset 0x607C there.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

SUPPORTED_METHODS = (1, 2, 17, 18, 19, 20, 21, 22, 35, 37)


@dataclass(frozen=True)
class Phase:
    direction: int  # +1 / -1
    fast: bool  # switch search speed (0x6099:1) or zero search speed (0x6099:2)
    signal: str  # "neg" | "pos" | "home" | "index"
    value: bool  # phase ends when signal == value (index: when a pulse is seen)


def method_phases(method: int, neg: bool, pos: bool, home: bool) -> list[Phase] | None:
    """Phases for a method given the switch states at start; None if unsupported."""
    P = Phase
    if method in (35, 37):
        return []
    if method in (1, 17):
        phases = [] if neg else [P(-1, True, "neg", True)]
        phases.append(P(+1, False, "neg", False))
        if method == 1:
            phases.append(P(+1, False, "index", True))
        return phases
    if method in (2, 18):
        phases = [] if pos else [P(+1, True, "pos", True)]
        phases.append(P(-1, False, "pos", False))
        if method == 2:
            phases.append(P(-1, False, "index", True))
        return phases
    # home switch methods; for 21/22 `home` is already the mirrored switch (active on the negative side)
    s = +1 if method in (19, 20) else -1
    if method in (19, 21):
        if home:
            return [P(-s, False, "home", False)]
        return [P(s, True, "home", True), P(-s, False, "home", False)]
    if method in (20, 22):
        if home:
            return [P(-s, True, "home", False), P(s, False, "home", True)]
        return [P(s, True, "home", True), P(-s, False, "home", False), P(s, False, "home", True)]
    return None


class HomingStatus(enum.Enum):
    IDLE = "idle"  # not started or interrupted: bits 13/12/10 = 0/0/1
    IN_PROGRESS = "in progress"  # 0/0/0
    RETURNING = "returning"  # home found, moving back to it: 0/0/0
    ATTAINED = "attained"  # 0/1/1 (at standstill)
    ERROR = "error"  # 1/0/x


@dataclass
class HomingRun:
    """The state of one homing procedure (stepped by the drive)."""

    method: int
    phases: list[Phase]
    start_m: float
    phase_index: int = 0
    status: HomingStatus = HomingStatus.IN_PROGRESS
    home_m: float = math.nan
    edge_m: float = math.nan  # where the last phase's signal was seen (the switch edge the next phase goes back to)
    error: str = ""

    @property
    def phase(self) -> Phase | None:
        return self.phases[self.phase_index] if self.phase_index < len(self.phases) else None


def index_crossed(x0_m: float, x1_m: float, offset_m: float, period_m: float) -> float | None:
    """The index-pulse position between x0 and x1 (exclusive of x0), or None."""
    if period_m <= 0 or x0_m == x1_m:
        return None
    k0 = math.floor((x0_m - offset_m) / period_m)
    k1 = math.floor((x1_m - offset_m) / period_m)
    if k0 == k1:
        return None
    k = k1 if x1_m > x0_m else k0
    return offset_m + k * period_m
