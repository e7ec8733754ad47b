"""Digital control loops (compiled): PI with conditional-integration anti-windup, quantisation.

Seed 000 section 2.3: u(k) = K_p e(k) + (K_p / T_i) sum_j e(j) T. The integral part is held when the output
is saturated and the error would drive it further into saturation (conditional integration).
"""

from __future__ import annotations

import math

from numba import njit

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)


@njit(cache=True, inline="always")
def pi_step(error: float, integral: float, kp: float, cycle_over_ti: float, limit: float) -> tuple:
    """One digital PI sample. Returns (output clamped to +-limit, new integral, saturated flag).

    ``integral`` is the sum of e(j) T / T_i (dimension of the error); ``cycle_over_ti`` = T / T_i is
    precomputed (0 means P only); ``limit`` <= 0 means no limit.
    """
    new_int = integral + error * cycle_over_ti
    out = kp * (error + new_int)
    sat = False
    if limit > 0.0:
        if out > limit:
            sat = True
            if error > 0.0:
                new_int = integral  # conditional integration: do not wind up further
            out = limit
        elif out < -limit:
            sat = True
            if error < 0.0:
                new_int = integral
            out = -limit
    return out, new_int, sat


def integral_gain_per_sample(cycle_s: float, ti_s: float) -> float:
    """T / T_i of a digital PI, 0 for a P controller (T_i = 0)."""
    return cycle_s / ti_s if ti_s > 0 else 0.0


@njit(cache=True, inline="always")
def quantise(value: float, quantum: float) -> float:
    """Floor to the sensor quantum (an encoder count); ``quantum`` <= 0 means ideal.

    A value of 2^52 quanta or more (or not finite) is returned as it is: the quantum is below its float
    resolution there, and ``math.floor`` of a compiled kernel returns an int64 that saturates, so a diverged
    (NaN or huge) position would read as a finite +-2^63 quanta and hide the divergence."""
    if quantum <= 0.0:
        return value
    q = value / quantum
    if not abs(q) < 4503599627370496.0:  # 2^52; False for NaN
        return value
    return quantum * math.floor(q)


@njit(cache=True, inline="always")
def clamp(value: float, limit: float) -> float:
    if limit <= 0.0:
        return value
    if value > limit:
        return limit
    if value < -limit:
        return -limit
    return value
