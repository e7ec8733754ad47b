"""Joint identification (seed 002 Sec. 3): eq. 26 objective, differential evolution on log10 parameters.

``MeasuredModes`` holds, per worktable position, the measured natural frequencies nf_t(p)(q) and peak
amplitudes amp_t(p)(q) (NaN where the paper has a gap, or where only frequencies are known). The
objective is eq. 26; a model mode that cannot be found in its band while the measurement has one counts
as a 100 % error for that term (so the optimiser is pushed away, never silently rewarded).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import differential_evolution

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)
from virtualaxis.rcsa import receptance as R
from virtualaxis.rcsa.params import JOINT_SYMBOLS, JointParams, RcsaModel
from virtualaxis.rcsa.peaks import GRID_POINTS_PER_BAND, find_model_modes, model_modes

MISSING_MODE_PENALTY = 1.0  # relative error charged for a measured mode the model does not show


@dataclass(frozen=True)
class MeasuredModes:
    """Measured modal data: positions [m] (P), frequencies [Hz] and amplitudes [m/N] (P x Q, NaN = gap)."""

    positions_m: np.ndarray
    frequencies_hz: np.ndarray
    amplitudes_m_per_n: np.ndarray

    def select(self, positions_m: Sequence[float], source: str = "measured data") -> MeasuredModes:
        """The rows at ``positions_m`` (matched within 0.1 mm); ValueError naming a missing position."""
        rows = []
        for pos in positions_m:
            hit = np.nonzero(np.abs(self.positions_m - pos) < 1e-4)[0]
            if hit.size == 0:
                have = ", ".join(f"{v:g}" for v in self.positions_m)
                raise ValueError(f"{source}: no data at position {pos:g} m (have {have})")
            rows.append(int(hit[0]))
        return MeasuredModes(self.positions_m[rows], self.frequencies_hz[rows], self.amplitudes_m_per_n[rows])


@njit(cache=True)
def _objective_terms(
    p: np.ndarray,
    positions_m: np.ndarray,
    bands_hz: np.ndarray,
    min_prominence: float,
    nf_t: np.ndarray,
    amp_t: np.ndarray,
    amplitude_weight: float,
    grid: np.ndarray,
    work: np.ndarray,
    nf_c: np.ndarray,
    amp_c: np.ndarray,
) -> float:
    """Sum of squared relative errors of eq. 26 (before the square root); the amplitude terms are
    multiplied by ``amplitude_weight`` (1 = eq. 26 as printed)."""
    total = 0.0
    for i in range(positions_m.shape[0]):
        model_modes(positions_m[i], p, bands_hz, min_prominence, grid, work, nf_c, amp_c)
        for q in range(bands_hz.shape[0]):
            if math.isfinite(nf_t[i, q]):
                if math.isfinite(nf_c[q]):
                    e = (nf_c[q] - nf_t[i, q]) / nf_t[i, q]
                else:
                    e = MISSING_MODE_PENALTY
                total += e * e
            if math.isfinite(amp_t[i, q]):
                if math.isfinite(amp_c[q]):
                    e = amplitude_weight * (amp_c[q] - amp_t[i, q]) / amp_t[i, q]
                else:
                    e = amplitude_weight * MISSING_MODE_PENALTY
                total += e * e
    return total


class Eq26Objective:
    """Picklable eq. 26 objective of log10(phi) for scipy's differential_evolution (parallel workers)."""

    def __init__(self, model: RcsaModel, measured: MeasuredModes, amplitude_weight: float = 1.0):
        n_modes = len(model.mode_bands_hz)
        if measured.frequencies_hz.shape[1] != n_modes:
            raise ValueError(
                f"measured data has {measured.frequencies_hz.shape[1]} mode orders,"
                f" the config has {n_modes} bands"
            )
        self.p_base = model.parameter_vector()
        self.positions_m = np.ascontiguousarray(measured.positions_m, dtype=np.float64)
        self.bands_hz = model.bands_array()
        self.min_prominence = float(model.min_peak_prominence)
        self.nf_t = np.ascontiguousarray(measured.frequencies_hz, dtype=np.float64)
        if not (math.isfinite(amplitude_weight) and amplitude_weight >= 0):
            raise ValueError(f"amplitude weight must be a number >= 0 (got {amplitude_weight!r})")
        self.amplitude_weight = float(amplitude_weight)
        use = amplitude_weight > 0
        amp = measured.amplitudes_m_per_n if use else np.full_like(self.nf_t, np.nan)
        self.amp_t = np.ascontiguousarray(amp, dtype=np.float64)
        self._scratch: tuple | None = None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_scratch"] = None
        return state

    def __call__(self, log10_phi: np.ndarray) -> float:
        if self._scratch is None:
            n = self.bands_hz.shape[0]
            self._scratch = (
                self.p_base.copy(),
                np.empty(GRID_POINTS_PER_BAND),
                np.empty((3, 3), dtype=np.complex128),
                np.empty(n),
                np.empty(n),
            )
        p, grid, work, nf_c, amp_c = self._scratch
        p[R.JOINT_SLICE] = 10.0 ** np.asarray(log10_phi, dtype=np.float64)
        total = _objective_terms(
            p,
            self.positions_m,
            self.bands_hz,
            self.min_prominence,
            self.nf_t,
            self.amp_t,
            self.amplitude_weight,
            grid,
            work,
            nf_c,
            amp_c,
        )
        return math.sqrt(total)

    def value_at(self, joints: JointParams) -> float:
        return self(np.log10(joints.as_array()))


@dataclass(frozen=True)
class IdentificationResult:
    joints: JointParams
    objective: float
    generations: int
    objective_evaluations: int
    wall_time_s: float
    converged_message: str


def identify_joints(
    model: RcsaModel,
    measured: MeasuredModes,
    *,
    lower: JointParams,
    upper: JointParams,
    population_per_parameter: int = 15,
    generations: int = 200,
    seed: int = 0,
    workers: int = 2,
    relative_tolerance: float = 0.0,
    amplitude_weight: float = 1.0,
    progress: Callable[[int], None] | None = None,
) -> IdentificationResult:
    """Minimise eq. 26 over log10 of the eight joint parameters with differential evolution.

    ``progress(generation)`` is called after every generation (for a progress bar)."""
    lo = np.log10(lower.as_array())
    hi = np.log10(upper.as_array())
    if not np.all(hi > lo):
        raise ValueError("every upper bound must exceed its lower bound")
    objective = Eq26Objective(model, measured, amplitude_weight)
    generation = [0]

    def _callback(intermediate_result: object) -> None:
        generation[0] += 1
        if progress is not None:
            progress(generation[0])

    t0 = time.perf_counter()
    res = differential_evolution(
        objective,
        list(zip(lo, hi, strict=True)),
        popsize=population_per_parameter,
        maxiter=generations,
        tol=relative_tolerance,
        rng=np.random.default_rng(seed),
        polish=False,
        init="latinhypercube",
        updating="deferred" if workers != 1 else "immediate",
        workers=workers,
        callback=_callback,
    )
    wall = time.perf_counter() - t0
    return IdentificationResult(
        joints=JointParams.from_array(10.0**res.x),
        objective=float(res.fun),
        generations=int(res.nit),
        objective_evaluations=int(res.nfev),
        wall_time_s=wall,
        converged_message=str(res.message),
    )


def frf_evaluations_per_objective(model: RcsaModel, measured: MeasuredModes, joints: JointParams) -> int:
    """How many h_6a6a evaluations one eq. 26 call makes at ``joints`` (for the benchmark's rate)."""
    p = model.parameter_vector(joints)
    bands = model.bands_array()
    total = 0
    for pos in measured.positions_m:
        n = bands.shape[0]
        total += model_modes(
            float(pos),
            p,
            bands,
            model.min_peak_prominence,
            np.empty(GRID_POINTS_PER_BAND),
            np.empty((3, 3), dtype=np.complex128),
            np.empty(n),
            np.empty(n),
        )
    return total


@dataclass(frozen=True)
class PositionPrediction:
    position_m: float
    natural_frequencies_hz: np.ndarray
    amplitudes_m_per_n: np.ndarray


def predict_modes(
    model: RcsaModel, positions_m: Sequence[float], joints: JointParams | None = None
) -> list[PositionPrediction]:
    """Natural frequencies and peak amplitudes per position from the receptance model (NaN = not found)."""
    p = model.parameter_vector(joints)
    bands = model.bands_array()
    out = []
    for pos in positions_m:
        model.check_position(float(pos))
        f, a = find_model_modes(float(pos), p, bands, model.min_peak_prominence)
        out.append(PositionPrediction(float(pos), f, a))
    return out


def relative_errors(predicted: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """|pred - meas| / meas per entry, NaN where either is missing."""
    with np.errstate(invalid="ignore"):
        return np.abs(predicted - measured) / measured


def overall_error(predicted: np.ndarray, measured: np.ndarray) -> float:
    """eq. 27: sqrt(sum delta(q)^2) over the orders that were measured. A measured mode missing from
    the prediction makes the result NaN (reported as a gap, not hidden)."""
    have = np.isfinite(measured)
    if np.any(have & ~np.isfinite(predicted)):
        return float("nan")
    rel = relative_errors(predicted[have], measured[have])
    return float(math.sqrt(np.sum(rel**2)))


__all__ = [
    "JOINT_SYMBOLS",
    "Eq26Objective",
    "IdentificationResult",
    "MeasuredModes",
    "PositionPrediction",
    "identify_joints",
    "overall_error",
    "predict_modes",
    "relative_errors",
]
