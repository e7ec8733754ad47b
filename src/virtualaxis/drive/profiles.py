"""Set-point generators of the drive, stepped once per position-loop cycle (all SI: m, m/s, m/s^2).

- :class:`PositionProfile`: online trapezoidal point-to-point generator (profile position mode, homing
  moves, stop ramps in position control). It re-plans every cycle from its present position and velocity,
  so a new target (change set immediately) or a halt takes effect at once, and it lands exactly on the
  target in discrete time.
- :class:`JerkFilter`: moving average over ``T_j = a / j``; applied to a trapezoidal profile it gives the
  jerk-limited (S-curve) profile with jerk a / T_j and the same end point (0x6086 = 3, jerk 0x60A4).
- :class:`VelocityRamp`: profile velocity mode ramp with separate acceleration / deceleration.
- :class:`LinearInterpolator`: cyclic synchronous targets interpolated over the interpolation time
  period 0x60C2.
- :class:`WindowTimer`: "condition true for at least T" (target reached, following error, ...).
"""

from __future__ import annotations

import math
from collections import deque

#: longest jerk filter [drive cycles] (chosen: 2^14, 16.4 s at a 1 ms cycle; its window is this many floats,
#: allocated once per set-point): a longer T_j = 0x6083 / 0x60A4 is refused, not planned
MAX_JERK_FILTER_CYCLES = 1 << 14


class PositionProfile:
    """Online trapezoid: state (position, velocity), target, v_max, a_max, d_max."""

    def __init__(self, dt_s: float, position_m: float = 0.0, velocity_m_s: float = 0.0):
        self.dt_s = dt_s
        self.position_m = position_m
        self.velocity_m_s = velocity_m_s
        self.target_m = position_m
        self.v_max = 0.1
        self.a_max = 1.0
        self.d_max = 1.0

    def reset(self, position_m: float, velocity_m_s: float = 0.0) -> None:
        self.position_m = position_m
        self.velocity_m_s = velocity_m_s
        self.target_m = position_m

    def set_target(self, target_m: float, v_max: float, a_max: float, d_max: float) -> None:
        self.target_m = target_m
        self.v_max = max(v_max, 1e-12)
        self.a_max = max(a_max, 1e-9)
        self.d_max = max(d_max, 1e-9)

    @property
    def done(self) -> bool:
        return self.position_m == self.target_m and self.velocity_m_s == 0.0

    def step(self) -> tuple[float, float]:
        """Advance one cycle; returns (position_m, velocity_m_s)."""
        dt = self.dt_s
        p, v = self.position_m, self.velocity_m_s
        e = self.target_m - p
        if e == 0.0 and v == 0.0:
            return p, v
        d = self.d_max
        # largest speed from which a discrete-time stop with decel d covers at most |e|
        dd = d * dt
        v_brake = -0.5 * dd + math.sqrt(0.25 * dd * dd + 2.0 * d * abs(e))
        v_des = math.copysign(min(self.v_max, v_brake), e)
        # accelerate with a_max when speeding up, decelerate with d_max when slowing down
        if v * v_des > 0 and abs(v_des) < abs(v) or v * v_des < 0 or v_des == 0.0:
            rate = d
        else:
            rate = self.a_max
        dv = v_des - v
        step = rate * dt
        v_new = v + (dv if abs(dv) <= step else math.copysign(step, dv))
        if v_new * e >= 0.0 and abs(e) <= abs(v_new) * dt:
            # the remaining distance fits into this cycle: land on the target
            self.position_m = self.target_m
            self.velocity_m_s = 0.0
            return self.position_m, 0.0
        self.velocity_m_s = v_new
        self.position_m = p + v_new * dt
        return self.position_m, v_new


class JerkFilter:
    """Moving average of the position over ``n`` cycles (n = 1: pass-through), at most
    :data:`MAX_JERK_FILTER_CYCLES`. Every call costs O(1); :meth:`reset` allocates ``n`` values."""

    def __init__(self) -> None:
        self._buf: deque[float] = deque()
        self._sum = 0.0
        self.n = 1
        self._last = 0.0  # the newest input
        self._run = 1  # how many of the newest inputs equal it (capped at n)

    def reset(self, position_m: float, n: int) -> None:
        n = int(n)
        if n > MAX_JERK_FILTER_CYCLES:
            raise ValueError(f"jerk filter of {n} cycles is longer than {MAX_JERK_FILTER_CYCLES}")
        self.n = max(1, n)
        self._buf = deque([position_m] * self.n)
        self._sum = position_m * self.n
        self._last, self._run = position_m, self.n

    def step(self, position_m: float) -> float:
        if position_m == self._last:
            if self._run < self.n:
                self._run += 1
        else:
            self._last, self._run = position_m, 1
        if self.n == 1:
            self._buf[0] = position_m
            return position_m
        self._sum += position_m - self._buf.popleft()
        self._buf.append(position_m)
        return self._sum / self.n

    def settled(self, position_m: float) -> bool:
        """Every value in the window equals ``position_m``."""
        return self._run >= self.n and self._last == position_m


class VelocityRamp:
    """Ramps a velocity set-point toward a target with acceleration / deceleration limits."""

    def __init__(self, dt_s: float):
        self.dt_s = dt_s
        self.velocity_m_s = 0.0

    def step(self, target_m_s: float, acc_m_s2: float, dec_m_s2: float) -> float:
        v = self.velocity_m_s
        speeding_up = target_m_s * v >= 0 and abs(target_m_s) > abs(v)
        rate = (acc_m_s2 if speeding_up else dec_m_s2) * self.dt_s
        dv = target_m_s - v
        self.velocity_m_s = v + (dv if abs(dv) <= rate else math.copysign(rate, dv))
        return self.velocity_m_s


class LinearInterpolator:
    """Interpolates cyclic targets: a new target starts a segment of ``n`` cycles from the previous one."""

    def __init__(self) -> None:
        self.start = 0.0
        self.end = 0.0
        self.n = 1
        self.i = 0

    def reset(self, value: float) -> None:
        self.start = self.end = value
        self.i = self.n

    def new_target(self, value: float, n_cycles: int) -> None:
        self.start = self.current()
        self.end = value
        self.n = max(1, n_cycles)
        self.i = 0

    def current(self) -> float:
        return self.start + (self.end - self.start) * (self.i / self.n)

    def step(self) -> tuple[float, float]:
        """Advance one cycle; returns (value, slope per cycle)."""
        if self.i < self.n:
            self.i += 1
            return self.current(), (self.end - self.start) / self.n
        return self.end, 0.0


class WindowTimer:
    """True once a condition has held for at least ``time_s`` (reset when it fails)."""

    def __init__(self) -> None:
        self.held_s = 0.0

    def update(self, condition: bool, dt_s: float, time_s: float) -> bool:
        if not condition:
            self.held_s = 0.0
            return False
        self.held_s += dt_s
        return self.held_s >= time_s - 1e-12


#: speed = 0 detection: a standstill shown is withdrawn at once above this multiple of the threshold 0x606F
#: (chosen: 4, the hysteresis band of SINAMICS p2150 against p2161 in its ratio; between 1x and 4x the speed
#: must stay above the threshold for the threshold time 0x6070)
SPEED_ZERO_HYSTERESIS = 4.0


class SpeedZeroDetector:
    """CiA 402 "speed = 0" (0x606F velocity threshold, 0x6070 threshold time) with hysteresis: set once |v| has
    stayed within the threshold for the threshold time; withdrawn once it has stayed above it for that time,
    or at once beyond :data:`SPEED_ZERO_HYSTERESIS` x the threshold. A settling axis whose speed swings about
    the threshold keeps one answer instead of toggling every few cycles."""

    def __init__(self) -> None:
        self.at_rest = False
        self._held_s = 0.0  # how long the opposite condition has held

    def reset(self) -> None:
        self.at_rest = False
        self._held_s = 0.0

    def update(self, speed_m_s: float, dt_s: float, threshold_m_s: float, time_s: float) -> bool:
        speed = abs(speed_m_s)
        if self.at_rest:
            if speed > SPEED_ZERO_HYSTERESIS * threshold_m_s:
                self._held_s, self.at_rest = 0.0, False
            elif speed > threshold_m_s:
                self._held_s += dt_s
                if self._held_s >= time_s - 1e-12:
                    self._held_s, self.at_rest = 0.0, False
            else:
                self._held_s = 0.0
        elif speed <= threshold_m_s:
            self._held_s += dt_s
            if self._held_s >= time_s - 1e-12:
                self._held_s, self.at_rest = 0.0, True
        else:
            self._held_s = 0.0
        return self.at_rest
