"""A tiny G-code interpolator for the example: G0 / G1 lines and G2 / G3 arcs (centre I, J relative to the start,
feed F in mm/min, absolute coordinates in mm), each block with a trapezoidal feed profile that starts and ends at
rest (exact stop, G61), sampled every interpolation cycle as a CSP set-point per axis.

Not part of the virtualaxis package: a user's controller under test."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

RAPID_MM_MIN = 6000.0  # G0 feed
ACCEL_MM_S2 = 1000.0  # path acceleration of every block (1 m/s^2)
WORD = re.compile(r"([GXYIJF])\s*([-+]?\d*\.?\d+)", re.IGNORECASE)


class GcodeError(ValueError):
    """A program line that cannot be run; the message names the line."""


@dataclass(frozen=True)
class Block:
    kind: str  # "line" | "arc"
    start: tuple[float, float]  # mm
    end: tuple[float, float]  # mm
    feed_mm_s: float
    centre: tuple[float, float] | None = None  # arcs
    ccw: bool = False  # G3

    @property
    def length_mm(self) -> float:
        if self.kind == "line":
            return math.dist(self.start, self.end)
        return abs(self._sweep()) * self._radius()

    def _radius(self) -> float:
        return math.dist(self.start, self.centre)

    def _sweep(self) -> float:
        cx, cy = self.centre
        a0 = math.atan2(self.start[1] - cy, self.start[0] - cx)
        a1 = math.atan2(self.end[1] - cy, self.end[0] - cx)
        sweep = a1 - a0
        if self.ccw and sweep <= 0:
            sweep += 2 * math.pi
        if not self.ccw and sweep >= 0:
            sweep -= 2 * math.pi
        return sweep

    def point(self, s_mm: float) -> tuple[float, float]:
        """The point at path length ``s_mm`` from the start."""
        total = self.length_mm
        u = 0.0 if total == 0 else min(max(s_mm / total, 0.0), 1.0)
        if self.kind == "line":
            return (self.start[0] + u * (self.end[0] - self.start[0]),
                    self.start[1] + u * (self.end[1] - self.start[1]))
        cx, cy = self.centre
        r = self._radius()
        a = math.atan2(self.start[1] - cy, self.start[0] - cx) + u * self._sweep()
        return (cx + r * math.cos(a), cy + r * math.sin(a))


def parse(program: str) -> list[Block]:
    """Blocks of a program (modal G and F; comments in parentheses or after ';')."""
    blocks: list[Block] = []
    pos = (0.0, 0.0)
    g, feed = 0, 0.0
    for number, raw in enumerate(program.splitlines(), 1):
        line = re.sub(r"\(.*?\)", "", raw.split(";")[0]).strip()
        if not line:
            continue
        words = {}
        for letter, value in WORD.findall(line):
            words[letter.upper()] = float(value)
        rest = WORD.sub("", line).strip()
        if rest:
            raise GcodeError(f"line {number}: cannot read {rest!r} in {raw!r}")
        if "G" in words:
            if words["G"] not in (0, 1, 2, 3):
                raise GcodeError(f"line {number}: G{words['G']:g} not supported (G0, G1, G2, G3)")
            g = int(words["G"])
        if "F" in words:
            if not words["F"] > 0:
                raise GcodeError(f"line {number}: feed F must be > 0 mm/min")
            feed = words["F"]
        end = (words.get("X", pos[0]), words.get("Y", pos[1]))
        f_mm_s = (RAPID_MM_MIN if g == 0 else feed) / 60.0
        if g != 0 and feed <= 0:
            raise GcodeError(f"line {number}: G{g} without a feed (F)")
        if g in (0, 1):
            blocks.append(Block("line", pos, end, f_mm_s))
        else:
            if "I" not in words and "J" not in words:
                raise GcodeError(f"line {number}: G{g} needs the centre I, J")
            centre = (pos[0] + words.get("I", 0.0), pos[1] + words.get("J", 0.0))
            if abs(math.dist(pos, centre) - math.dist(end, centre)) > 1e-3:
                raise GcodeError(f"line {number}: end point not on the arc (radius differs by more than 1 um)")
            blocks.append(Block("arc", pos, end, f_mm_s, centre, ccw=(g == 3)))
        pos = end
    return blocks


def interpolate(blocks: list[Block], cycle_s: float = 0.001) -> np.ndarray:
    """Set-points [mm], shape (n, 2): one per cycle, trapezoidal feed per block, a few cycles of rest at the
    end."""
    points: list[tuple[float, float]] = []
    for b in blocks:
        length = b.length_mm
        if length == 0:
            continue
        v, a = b.feed_mm_s, ACCEL_MM_S2
        t_acc = v / a
        if v * t_acc > length:  # triangle
            t_acc = math.sqrt(length / a)
            v = a * t_acc
        t_const = (length - v * t_acc) / v
        total = 2 * t_acc + t_const
        n = max(1, math.ceil(total / cycle_s))
        for i in range(1, n + 1):
            t = min(i * cycle_s, total)
            if t < t_acc:
                s = 0.5 * a * t * t
            elif t < t_acc + t_const:
                s = 0.5 * a * t_acc * t_acc + v * (t - t_acc)
            else:
                td = total - t
                s = length - 0.5 * a * td * td
            points.append(b.point(s))
    points += [points[-1]] * 50
    return np.asarray(points)


def contour_error_mm(command: np.ndarray, actual: np.ndarray, window: int = 400) -> np.ndarray:
    """Distance [mm] of each actual point to the commanded path (segments between consecutive commanded
    points, searched among the ``window`` samples before and a few after its own)."""
    n = len(actual)
    out = np.empty(n)
    for k in range(n):
        lo, hi = max(0, k - window), min(len(command) - 1, k + 5)
        p0, p1 = command[lo:hi], command[lo + 1:hi + 1]
        if len(p0) == 0:
            out[k] = float(np.linalg.norm(actual[k] - command[min(k, len(command) - 1)]))
            continue
        d = p1 - p0
        L2 = np.einsum("ij,ij->i", d, d)
        u = np.where(L2 > 0, np.einsum("ij,ij->i", actual[k] - p0, d) / np.where(L2 > 0, L2, 1), 0.0)
        u = np.clip(u, 0.0, 1.0)
        nearest = p0 + u[:, None] * d
        out[k] = float(np.min(np.linalg.norm(actual[k] - nearest, axis=1)))
    return out
