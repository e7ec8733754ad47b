"""Position commands of the reference cases, sampled at the position-loop rate (1 kHz).

All commands start and end at rest and are preceded by a standstill (the axis enabled and holding). Units:
metres, seconds; feeds are given in mm/min like the CNC programs of seed 000.
"""

from __future__ import annotations

import numpy as np


def sine(feed_mm_min: float, stroke_m: float, periods: float, t_s: float = 1e-3, hold_s: float = 0.3) -> np.ndarray:
    """x = -A cos(w t) about table 0 with A = stroke / 2 and peak speed = feed; starts at -A at rest
    (zero velocity, acceleration A w^2 steps on, as a CNC sine program does), ``periods`` periods long."""
    amp = stroke_m / 2.0
    w = feed_mm_min / 60e3 / amp
    dur = periods * 2 * np.pi / w
    t = np.arange(int(round(dur / t_s)) + 1) * t_s
    x = -amp * np.cos(w * t)
    return np.concatenate([np.full(int(round(hold_s / t_s)), -amp), x, np.full(int(round(hold_s / t_s)), x[-1])])


def _s_curve(distance_m: float, v_max: float, a_max: float, j_max: float, t_s: float) -> np.ndarray:
    """Jerk-limited point-to-point displacement 0 -> distance (sign kept): a trapezoidal velocity profile
    (acceleration-limited) smoothed by a moving average of length a_max / j_max, which bounds the jerk and
    keeps the distance exact. Returns positions from 0 to distance, one per ``t_s``."""
    d = abs(distance_m)
    sgn = 1.0 if distance_m >= 0 else -1.0
    t_acc = v_max / a_max
    if a_max * t_acc**2 > d:  # triangular profile
        t_acc = np.sqrt(d / a_max)
        v_max = a_max * t_acc
    t_const = d / v_max - t_acc
    t_tot = 2 * t_acc + t_const
    n = int(np.ceil(t_tot / t_s)) + 1
    t = np.arange(n) * t_s
    v = np.minimum(np.minimum(a_max * t, v_max), np.maximum(a_max * (t_tot - t), 0.0))
    n_j = max(int(round(a_max / j_max / t_s)), 1)
    if n_j > 1:
        v = np.convolve(np.concatenate([v, np.zeros(n_j)]), np.ones(n_j) / n_j)[: n + n_j]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1])) * t_s])
    x *= d / x[-1] if x[-1] > 0 else 1.0
    return sgn * x


def point_to_point(start_m: float, end_m: float, v_m_s: float, a_m_s2: float, j_m_s3: float,
                   dwell_s: float = 0.5, t_s: float = 1e-3, hold_s: float = 0.3) -> np.ndarray:
    """Move start -> end, dwell, end -> start (jerk-limited), with standstill before and after."""
    there = start_m + _s_curve(end_m - start_m, v_m_s, a_m_s2, j_m_s3, t_s)
    back = end_m + _s_curve(start_m - end_m, v_m_s, a_m_s2, j_m_s3, t_s)
    parts = [np.full(int(round(hold_s / t_s)), start_m), there, np.full(int(round(dwell_s / t_s)), end_m), back,
             np.full(int(round(hold_s / t_s)), start_m)]
    return np.concatenate(parts)


def velocity(x: np.ndarray, t_s: float = 1e-3) -> np.ndarray:
    """Backward-difference command speed [m/s] (0 at the first sample)."""
    v = np.zeros_like(x)
    v[1:] = np.diff(x) / t_s
    return v


def force_pulses(n: int, amplitude_n: float, width_s: float, period_s: float, first_s: float,
                 t_s: float = 1e-3) -> np.ndarray:
    """Known external force on the table [N]: rectangular pulses of ``width_s`` every ``period_s`` from
    ``first_s`` on, alternating in sign (a validation run with force pulses, like a lab axis under pulse loads)."""
    t = np.arange(n) * t_s
    f = np.zeros(n)
    k = 0
    start = first_s
    while start < t[-1]:
        f[(t >= start) & (t < start + width_s)] = amplitude_n * (1 if k % 2 == 0 else -1)
        start += period_s
        k += 1
    return f
