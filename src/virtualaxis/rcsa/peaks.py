"""Natural frequencies and peak amplitudes of h_all-6a6a, one per mode band (seed 002 Sec. 4.1).

The paper takes the natural frequency as the peak of the table FRF near where each mode is expected
(Fig. 10). Here each mode order has a search band [low_hz, high_hz]: the largest |h| on a logarithmic
grid inside the band must be an interior maximum standing out by ``min_prominence`` (relative to the
lower of the two band-edge-side minima), and is then refined by golden-section search. A band without
such a peak yields NaN -- a gap, like the paper's "—" at l4 -- never the band edge.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)
from virtualaxis.rcsa.receptance import table_receptance

GRID_POINTS_PER_BAND = 100
GOLDEN_ITERATIONS = 25
_INV_PHI = 0.6180339887498949


@njit(cache=True)
def _abs_h(f_hz: float, position_m: float, p: np.ndarray, work: np.ndarray) -> float:
    return abs(table_receptance(2.0 * math.pi * f_hz, position_m, p, work))


@njit(cache=True)
def model_modes(
    position_m: float,
    p: np.ndarray,
    bands_hz: np.ndarray,
    min_prominence: float,
    grid: np.ndarray,
    work: np.ndarray,
    freq_out: np.ndarray,
    amp_out: np.ndarray,
) -> int:
    """Peak frequency [Hz] and |h| [m/N] per band into ``freq_out``/``amp_out`` (NaN if none).

    ``grid`` (float64[GRID_POINTS_PER_BAND]) and ``work`` (complex128[3, 3]) are scratch arrays.
    Returns the number of FRF evaluations made."""
    n_grid = grid.shape[0]
    evals = 0
    for b in range(bands_hz.shape[0]):
        lo = bands_hz[b, 0]
        hi = bands_hz[b, 1]
        ratio = math.log(hi / lo) / (n_grid - 1)
        best = 0
        for k in range(n_grid):
            grid[k] = _abs_h(lo * math.exp(ratio * k), position_m, p, work)
            if grid[k] > grid[best]:
                best = k
        evals += n_grid
        freq_out[b] = np.nan
        amp_out[b] = np.nan
        if best == 0 or best == n_grid - 1 or not math.isfinite(grid[best]):
            continue
        left_min = grid[0]
        for k in range(best):
            left_min = min(left_min, grid[k])
        right_min = grid[best]
        for k in range(best, n_grid):
            right_min = min(right_min, grid[k])
        if grid[best] < (1.0 + min_prominence) * max(left_min, right_min):
            continue
        # golden-section refinement of the maximum on [f_{best-1}, f_{best+1}]
        a = lo * math.exp(ratio * (best - 1))
        c = lo * math.exp(ratio * (best + 1))
        x1 = c - _INV_PHI * (c - a)
        x2 = a + _INV_PHI * (c - a)
        f1 = _abs_h(x1, position_m, p, work)
        f2 = _abs_h(x2, position_m, p, work)
        for _ in range(GOLDEN_ITERATIONS):
            if f1 > f2:
                c = x2
                x2 = x1
                f2 = f1
                x1 = c - _INV_PHI * (c - a)
                f1 = _abs_h(x1, position_m, p, work)
            else:
                a = x1
                x1 = x2
                f1 = f2
                x2 = a + _INV_PHI * (c - a)
                f2 = _abs_h(x2, position_m, p, work)
        evals += GOLDEN_ITERATIONS + 2
        if f1 > f2:
            freq_out[b] = x1
            amp_out[b] = f1
        else:
            freq_out[b] = x2
            amp_out[b] = f2
        if amp_out[b] < grid[best]:  # refinement cannot lose the grid maximum
            freq_out[b] = lo * math.exp(ratio * best)
            amp_out[b] = grid[best]
    return evals


def find_model_modes(
    position_m: float, p: np.ndarray, bands_hz: np.ndarray, min_prominence: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Convenience wrapper: (natural frequencies [Hz], amplitudes [m/N]) per band, NaN for gaps."""
    n = bands_hz.shape[0]
    freq = np.empty(n)
    amp = np.empty(n)
    model_modes(
        float(position_m),
        p,
        np.ascontiguousarray(bands_hz, dtype=np.float64),
        float(min_prominence),
        np.empty(GRID_POINTS_PER_BAND),
        np.empty((3, 3), dtype=np.complex128),
        freq,
        amp,
    )
    return freq, amp


PEAK_FIT_LEVEL = 0.7  # samples above this fraction of the maximum enter the peak fit
PEAK_FIT_HALF_WIDTH = 8  # at most this many samples either side of the maximum


def _fit_peak(freq_hz: np.ndarray, mag: np.ndarray, k: int) -> tuple[float, float]:
    """Least-squares parabola through log|h| over the contiguous samples around the maximum ``k`` that
    stay above PEAK_FIT_LEVEL of it (at least the three nearest): averages out measurement noise."""
    lo = k
    while lo > 0 and k - lo < PEAK_FIT_HALF_WIDTH and mag[lo - 1] >= PEAK_FIT_LEVEL * mag[k]:
        lo -= 1
    hi = k
    while hi < mag.size - 1 and hi - k < PEAK_FIT_HALF_WIDTH and mag[hi + 1] >= PEAK_FIT_LEVEL * mag[k]:
        hi += 1
    lo, hi = min(lo, k - 1), max(hi, k + 1)
    x = freq_hz[lo : hi + 1] - freq_hz[k]
    y = np.log(mag[lo : hi + 1])
    a2, a1, a0 = np.polyfit(x, y, 2)
    if not a2 < 0:
        return float(freq_hz[k]), float(mag[k])
    x_peak = float(np.clip(-a1 / (2 * a2), x[0], x[-1]))
    return float(freq_hz[k] + x_peak), float(np.exp(a0 + a1 * x_peak + a2 * x_peak**2))


def measured_modes(
    freq_hz: np.ndarray, magnitude: np.ndarray, bands_hz: np.ndarray, min_prominence: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Peak per band in a sampled (measured) FRF magnitude, refined by a least-squares parabola on
    log|h| around the maximum (:func:`_fit_peak`). NaN where a band has no interior, prominent maximum
    or fewer than three samples."""
    n = bands_hz.shape[0]
    out_f = np.full(n, np.nan)
    out_a = np.full(n, np.nan)
    for b, (lo, hi) in enumerate(bands_hz):
        idx = np.nonzero((freq_hz >= lo) & (freq_hz <= hi))[0]
        if idx.size < 3:
            continue
        mag = magnitude[idx]
        k = int(np.argmax(mag))
        if k == 0 or k == idx.size - 1:
            continue
        floor = max(mag[:k].min(), mag[k:].min())
        if mag[k] < (1.0 + min_prominence) * floor:
            continue
        out_f[b], out_a[b] = _fit_peak(freq_hz[idx], mag, k)
    return out_f, out_a
