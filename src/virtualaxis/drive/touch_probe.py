"""Touch probe (CiA 402 0x60B8 function, 0x60B9 status, 0x60BA-0x60BD latched positions): the position feedback
latched at an edge of a probe input or of the encoder's index pulse.

Inputs: probe input 1 / 2 (0x60FD bit 16 / 17) is active while the position feedback is at or above its
switching position 0x2014:1 / :2 (machine coordinate: plant position in position units, 0x7FFFFFFF: never; a
measuring probe touching a workpiece) or while the master forces it (0x2014:3 bit 0 / 1). The index pulse
(source 1) comes once per motor revolution, as homing sees it.

Timing: an edge is timed at the plant's inner rate, the current-loop cycles of one drive cycle (N = current
cycles per position cycle): the feedback is interpolated between the two drive-cycle samples, the edge falls on
the first inner sample at or past the crossing, and the position latched is the feedback there (not the
drive-cycle sample). An edge forced by the master falls on the start of the cycle after the write.

0x60B8, per probe (probe 2: the same bits + 8): bit 0 enable, bit 1 continuous (0: first edge only), bits 2-3
source (0 probe input, 1 index pulse; others refused), bit 4 / 5 latch at the positive / negative edge.
0x60B9: bit 0 enabled, bit 1 / 2 positive / negative edge position stored, bit 6 / 7 toggled by every positive
/ negative edge stored (continuous mode). Enabling a probe (bit 0 rising) or an edge (bit 4 / 5 rising) re-arms
it and clears its stored bits; disabling a probe clears its status, disabling an edge (bit 4 / 5 cleared) that
edge's stored and toggle bits (0x60BA-0x60BD keep the positions last latched).
"""

from __future__ import annotations

import math

from virtualaxis.drive.homing import index_crossed

#: 0x2014:1/2 value of a probe input that never switches
INPUT_NEVER = 0x7FFFFFFF
#: the latched-position objects: (probe, edge) -> index (edge 0 positive, 1 negative)
LATCH_INDEX = {(0, 0): 0x60BA, (0, 1): 0x60BB, (1, 0): 0x60BC, (1, 1): 0x60BD}


def check_function(value: int) -> str | None:
    """Why a touch probe function 0x60B8 value is refused (None: accepted)."""
    for probe in (0, 1):
        source = value >> (8 * probe + 2) & 0x3
        if source > 1:
            return (f"touch probe {probe + 1} trigger source {source} (0x60B8 bits {8 * probe + 2}-{8 * probe + 3}) is "
                    "not offered: 0 probe input, 1 encoder index pulse")
    return None


class TouchProbe:
    """Two touch probes of one drive. ``inner_steps``: inner (current-loop) samples per drive cycle;
    ``index_offset_m`` / ``index_period_m``: the index pulse positions (plant coordinate)."""

    def __init__(self, inner_steps: int, index_offset_m: float, index_period_m: float) -> None:
        self.inner_steps = max(1, int(inner_steps))
        self.index_offset_m = index_offset_m
        self.index_period_m = index_period_m
        self.function = 0
        self.status = 0
        self.switch_at_m: list[float | None] = [None, None]  # probe input switching positions (plant) [m]
        self.forced = 0  # 0x2014:3
        self.levels = 0  # the inputs' levels now (bit 0 / 1)
        #: latched positions not yet taken by the drive: [(probe, edge, plant position [m])]
        self.latched: list[tuple[int, int, float]] = []

    @property
    def input_bits(self) -> int:
        """The probe inputs as 0x60FD shows them (bit 16 / 17)."""
        return self.levels << 16

    @property
    def idle(self) -> bool:
        """Nothing to watch: no probe enabled, no input that can switch."""
        return not (self.function & 0x101 or self.forced or self.levels
                    or self.switch_at_m[0] is not None or self.switch_at_m[1] is not None)

    def configure_inputs(self, switch_units: tuple[int, int], forced: int, u: float) -> None:
        """0x2014:1 / :2 (position units; :data:`INPUT_NEVER`: never) and 0x2014:3; ``u`` metres per unit."""
        self.switch_at_m = [None if s == INPUT_NEVER else s * u for s in switch_units]
        self.forced = forced & 0x3

    def set_function(self, value: int) -> None:
        """0x60B8 written: enable / disable / re-arm each probe (status bits as the module docstring says)."""
        old, self.function = self.function, value
        status = self.status
        for probe in (0, 1):
            shift = 8 * probe
            f, o = value >> shift, old >> shift
            if not f & 0x1:
                status &= ~(0xFF << shift)
                continue
            status |= 0x1 << shift
            if not o & 0x1:
                status &= ~(0xC6 << shift)  # enabled: nothing stored yet
            else:
                for edge in (0, 1):
                    if f & (0x10 << edge) and not o & (0x10 << edge):
                        status &= ~((0x2 << edge) << shift)  # this edge re-armed
                    elif not f & (0x10 << edge):
                        status &= ~((0x42 << edge) << shift)  # this edge disabled: stored and toggle bits off
        self.status = status

    def _level(self, n: int, x_m: float) -> bool:
        at = self.switch_at_m[n]
        return bool(self.forced >> n & 1) or (at is not None and x_m >= at)

    def cycle(self, x0_m: float, x1_m: float) -> bool:
        """One drive cycle in which the position feedback went from ``x0_m`` to ``x1_m`` (plant coordinate):
        edges found, enabled ones latched into :attr:`latched`; returns whether the status changed."""
        n_inner = self.inner_steps
        dx = x1_m - x0_m
        old_status = self.status
        levels = 0
        for n in (0, 1):
            before = bool(self.levels >> n & 1)
            forced = bool(self.forced >> n & 1)
            at = self.switch_at_m[n]
            edges: list[tuple[bool, float]] = []  # (rising, plant position at the edge)
            start = forced or (at is not None and x0_m >= at)
            if start != before:  # a change since the last cycle's end (a forced input): at the cycle start
                edges.append((start, x0_m))
            end = forced or (at is not None and x1_m >= at)
            if end != start and dx != 0.0 and at is not None:
                j = min(n_inner, max(0, math.ceil((at - x0_m) / dx * n_inner - 1e-9)))
                edges.append((end, x0_m + dx * j / n_inner))
            if end:
                levels |= 1 << n
            f = self.function >> (8 * n)
            if not f & 0x1:
                continue
            if f >> 2 & 0x3 == 1:  # the encoder's index pulse: a pulse (both edges) at each mark passed
                edges = []
                crossing = index_crossed(x0_m, x1_m, self.index_offset_m, self.index_period_m)
                if crossing is not None:
                    j = min(n_inner, max(1, math.ceil((crossing - x0_m) / dx * n_inner - 1e-9)))
                    x = x0_m + dx * j / n_inner
                    edges = [(True, x), (False, x)]
            for rising, x in edges:
                self._latch(n, 0 if rising else 1, x, f)
        self.levels = levels
        return self.status != old_status

    def _latch(self, probe: int, edge: int, x_m: float, f: int) -> None:
        if not f & (0x10 << edge):
            return
        shift = 8 * probe
        stored = (0x2 << edge) << shift
        if not f & 0x2 and self.status & stored:
            return  # first edge only: already stored
        self.status |= stored
        if f & 0x2:
            self.status ^= (0x40 << edge) << shift
        self.latched.append((probe, edge, x_m))
