"""Fitting candidate effects (choosing among them: :mod:`virtualaxis.diagnosis.selection`).

One candidate fit (:func:`fit_candidate`, a top-level function so that it runs in a process pool or
on Dask workers): starting values from the effect's ``starts`` (some informed by the localisation,
e.g. spectral peaks for a resonance) are screened with one simulation each; the best start is refined
with ``scipy.optimize.least_squares`` (trust-region reflective, bounds, finite-difference Jacobian)
on the weighted residuals of the *fit* traces; ``method="de"`` uses ``differential_evolution``
instead (slow, for multi-modal cases). The fitted model is then simulated on the *held-out* traces.

The settings (:class:`FitSettings`) hold the selection's thresholds too; the process pool or Dask cluster that
runs the fits is a :class:`Runner`.
"""

from __future__ import annotations

import math
import os
import signal
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize
from scipy.ndimage import uniform_filter1d

from virtualaxis.config import AxisConfig
from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.data import (
    SimulateFn,
    TraceData,
    Weights,
    perturbed_command,
    pooled_metrics,
    residuals,
    simulate_trace,
    weighted_ssr,
)
from virtualaxis.diagnosis.where import Localisation, localise, signature_overlap


@dataclass
class FitSettings:
    max_nfev: int = 4  # least-squares function evaluations in refinement (Jacobians come on top)
    max_samples_per_trace: int = 4000  # fit residuals are decimated to at most this many per channel
    method: str = "gn"  # "gn" (Gauss-Newton, lsq_linear steps) | "lsq" (least_squares) | "de" (diff. evolution)
    max_iter: int = 5  # Gauss-Newton iterations
    polish_nfev: int = 24  # simulations of the derivative-free polish after Gauss-Newton (0 = none),
    #                        plus 12 for every further parameter
    joint_refit: bool = True  # refit all accepted effects together at the end
    pattern_nfev: int = 12  # simulations per parameter of the coarse-to-fine compass search after the polish
    alt_starts: int = 2  # refine also from the next-best screening starts with a different shape (resonance)
    min_gain: float = 0.10  # held-out weighted residual energy must fall by 10 % of what is left ...
    min_gain_total: float = 0.02  # ... and by 2 % of the nominal model's (no fitting of leftovers)
    min_screen_gain: float = 0.03  # a candidate must explain 3 % of the fit residual to be refined
    refine_top: int = 6  # candidates refined (and judged on held-out data) per round
    min_signature_overlap: float = 0.5
    max_channel_loss: float = -0.25  # no measured channel may get more than 25 % worse (energy) held out
    max_rounds: int = 4
    jacobian_step: float = 0.15  # secant step in internal units (15 % of the typical size)
    smoothing_s: float = 0.003  # fit residuals are averaged over 3 ms (impact/chatter detail is not
    #                             reproducible sample by sample; first zero of the filter at 333 Hz)
    parsimony: float = 0.05  # a candidate with fewer parameters wins if it leaves at most 5 % more energy


@dataclass
class FitJob:
    """Everything a worker needs (picklable)."""

    effect: str
    cfg: AxisConfig
    traces: list[TraceData]
    fit_idx: list[int]
    holdout_idx: list[int]
    weights: Weights
    hints: dict
    settings: FitSettings
    simulate: SimulateFn
    stage: str = "screen"  # "screen" | "refine"
    base_preds: dict = field(default_factory=dict)  # trace index -> current model prediction
    start: dict = field(default_factory=dict)  # refine: the screening estimate
    alt_starts: list[dict] = field(default_factory=list)  # refine: further starts (multi-modal shapes)
    target: Localisation | None = None  # where the current residual lies
    target_channel: str = ""


@dataclass
class CandidateResult:
    effect: str
    values: dict[str, float]
    stderr: dict[str, float]
    fit_ssr: dict[str, float]
    holdout_ssr: dict[str, float]
    fit_metrics: dict[str, dict[str, float]]
    holdout_metrics: dict[str, dict[str, float]]
    signature_overlap: float
    n_sims: int
    seconds: float
    at_bound: list[str] = field(default_factory=list)
    error: str = ""
    stage: str = "screen"
    screen_gain: float = 0.0  # fraction of the weighted fit residual energy explained (screening)
    alternatives: list[dict] = field(default_factory=list)  # next-best screening starts (other shapes)


class _Model:
    """Maps internal parameter vectors to configs and weighted residual vectors."""

    def __init__(self, job: FitJob):
        self.job = job
        self.effect = fx.effect_of(job.effect)
        self.params = self.effect.params(job.cfg)
        self.fixed: dict[str, float] = {}
        self.free = [p for p in self.params if not fx.is_discrete(p.name)]
        self.n_sims = 0
        self.decim = []
        self.trace_rows: list[slice] = []
        self._cache: dict[tuple, np.ndarray] = {}
        self.tried: list[tuple[float, dict[str, float]]] = []  # screening: (cost, estimate) per start
        self.smooth = []
        for i in job.fit_idx:
            n = job.traces[i].t.size
            self.decim.append(max(1, int(math.ceil(n / job.settings.max_samples_per_trace))))
            dt = float(job.traces[i].t[1] - job.traces[i].t[0])
            self.smooth.append(max(1, int(round(job.settings.smoothing_s / dt))))

    def nominal_values(self) -> dict[str, float]:
        return {p.name: min(max(p.nominal, p.lower), p.upper) for p in self.params}

    def values(self, u: np.ndarray) -> dict[str, float]:
        v = {p.name: p.from_internal(float(x)) for p, x in zip(self.free, u, strict=True)}
        v.update(self.fixed)
        return v

    def cfg(self, u: np.ndarray) -> AxisConfig:
        return self.effect.apply(self.job.cfg, self.values(u))

    def predict(self, cfg: AxisConfig, idx: list[int]) -> list[dict[str, np.ndarray]]:
        out = []
        for i in idx:
            out.append(simulate_trace(cfg, self.job.traces[i], self.job.simulate))
            self.n_sims += 1
        return out

    def stack(self, preds: list[dict[str, np.ndarray]]) -> np.ndarray:
        """Weighted, decimated residual vector of the fit traces."""
        w = self.job.weights
        parts = []
        rows, pos = [], 0
        for k, (i, pred) in enumerate(zip(self.job.fit_idx, preds, strict=True)):
            td = self.job.traces[i]
            d = self.decim[k]
            start = pos
            for ch in sorted(td.measured):
                if ch in pred and ch in w.sigma:
                    r = uniform_filter1d(td.measured[ch] - pred[ch], self.smooth[k])
                    parts.append(r[::d] / w.sigma[ch] * math.sqrt(d))
                    pos += parts[-1].size
            if pos > start:
                rows.append(slice(start, pos))
        self.trace_rows = rows  # rows of each fit trace in the vector (independent chaos per trace)
        return np.concatenate(parts) if parts else np.zeros(1)

    def residual_of_values(self, values: dict[str, float]) -> np.ndarray | None:
        try:
            vec = self.stack(self.predict(self.effect.apply(self.job.cfg, values), self.job.fit_idx))
        except Exception:  # a config the simulator or the schema rejects
            return None
        return vec if np.all(np.isfinite(vec)) else None

    def residual_vector(self, u: np.ndarray) -> np.ndarray:
        key = (np.asarray(u, dtype=float).tobytes(), tuple(sorted(self.fixed.items())))
        if key not in self._cache:
            r = self.residual_of_values(self.values(u))
            self._cache[key] = r if r is not None else np.full(self.size, 1e3)
        return self._cache[key]

    def jacobian_steps(self, u: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Secant step per free parameter in internal units, ``scale`` x the settings' step (sign: towards the
        inside of the bounds; shortened to the room there is)."""
        lo, hi = self.bounds()
        h = scale * np.array([self.job.settings.jacobian_step * (max(1.0, abs(x)) if p.scale == "lin" else 1.0)
                              for p, x in zip(self.free, u, strict=True)])
        up, down = hi - u, u - lo
        return np.where(u + h <= hi, h, np.where(u - h >= lo, -h, np.where(up >= down, up, -down)))

    def secant_jacobian(self, u: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Finite differences with a large step (the simulated response is not smooth at small scales)."""
        f0 = self.residual_vector(u)
        cols = []
        for j, h in enumerate(self.jacobian_steps(u, scale)):
            uj = u.copy()
            uj[j] += h
            cols.append((self.residual_vector(uj) - f0) / h)
        return np.column_stack(cols)

    def chaos_difference(self, u: np.ndarray, seed: int = 1) -> np.ndarray | None:
        """How the weighted fit residual at ``u`` changes when the commands change by an unmeasurably small
        white perturbation (:func:`~virtualaxis.diagnosis.data.perturbed_command`): one draw of the model's own
        chaos, at the size every secant Jacobian column carries on top of the parameter's real effect. None if
        it cannot be simulated."""
        rng = np.random.default_rng(seed)
        cfg = self.cfg(u)
        preds = []
        try:
            for i in self.job.fit_idx:
                preds.append(simulate_trace(cfg, perturbed_command(self.job.traces[i], rng), self.job.simulate))
                self.n_sims += 1
        except Exception:  # a config the simulator rejects: no correction
            return None
        d = self.stack(preds) - self.residual_vector(u)
        return d if d.shape == (self.size,) and np.all(np.isfinite(d)) else None

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([p.internal_bounds()[0] for p in self.free]),
                np.array([p.internal_bounds()[1] for p in self.free]))

    def internal(self, values: dict[str, float]) -> np.ndarray:
        lo, hi = self.bounds()
        u = np.array([p.to_internal(min(max(values[p.name], p.lower), p.upper)) for p in self.free])
        return np.clip(u, lo, hi)


def screen(job: FitJob, model: _Model) -> tuple[dict[str, float], float, float]:
    """One secant Gauss-Newton step from the current model per start point: the columns are the
    responses to each amplitude parameter moved to its start value (shape parameters at the start's
    values); a bounded linear least-squares fit of those columns to the residual gives the estimate.
    Returns (values, explained fraction of the residual energy, cost)."""
    base = model.stack([job.base_preds[i] for i in job.fit_idx])
    model.size = base.size
    r0 = float(base @ base)
    nominal = model.nominal_values()
    best: tuple[dict[str, float], float, float] = (nominal, 0.0, r0)
    for st in model.effect.starts(job.cfg, job.hints) or [{}]:
        anchor = {**nominal, **st}
        shape = {p.name: anchor[p.name] for p in model.params if p.shape or fx.is_discrete(p.name)}
        amp = [p for p in model.free if not p.shape and anchor[p.name] != nominal[p.name]]
        if not amp:
            continue
        cols, lo, hi = [], [], []
        for p in amp:
            vals = {**nominal, **shape, p.name: anchor[p.name]}
            r = model.residual_of_values(vals)
            if r is None:
                continue
            cols.append(base - r)  # the model change this column makes (weighted)
            d = anchor[p.name] - nominal[p.name]
            a, b = (p.lower - nominal[p.name]) / d, (p.upper - nominal[p.name]) / d
            lo.append(min(a, b))
            hi.append(max(a, b))
        if not cols:
            continue
        a_mat = np.column_stack(cols)
        sol = optimize.lsq_linear(a_mat, base, bounds=(np.array(lo), np.array(hi)))
        resid = base - a_mat @ sol.x
        cost = float(resid @ resid)
        vals = {**nominal, **shape}
        for p, alpha in zip(amp, sol.x, strict=False):
            vals[p.name] = float(min(max(nominal[p.name] + alpha * (anchor[p.name] - nominal[p.name]),
                                         p.lower), p.upper))
        model.tried.append((cost, vals))
        if cost < best[2]:
            best = (vals, 1.0 - cost / max(r0, 1e-300), cost)
    return best


def _alternative_starts(model: _Model, best: dict[str, float], n: int) -> list[dict[str, float]]:
    """The next-best screening estimates whose shape parameters (a resonance's frequency, a Stribeck
    velocity, a cogging order) differ by more than 15 % from the best's and from each other: a cost with
    several basins over a shape parameter is refined from each, and the best fit is kept."""
    shape = [p.name for p in model.params if p.shape or fx.is_discrete(p.name)]
    if n <= 0 or not shape:
        return []
    chosen = [best]
    out = []
    for _, vals in sorted(model.tried, key=lambda cv: cv[0]):
        if len(out) >= n:
            break
        if all(any(abs(vals[k] - c[k]) > 0.15 * max(abs(c[k]), 1e-300) for k in shape) for c in chosen):
            chosen.append(vals)
            out.append(vals)
    return out


def gauss_newton(model: _Model, u0: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_iter: int):
    """Bounded Gauss-Newton with a secant Jacobian: each step solves the linearised problem with
    ``scipy.optimize.lsq_linear`` inside the bounds, then backtracks (1, 1/2, 1/4) until the cost falls."""
    u = u0.copy()
    f = model.residual_vector(u)
    cost = float(f @ f)
    jac = None
    for _ in range(max_iter):
        jac = model.secant_jacobian(u)
        step = optimize.lsq_linear(jac, -f, bounds=(lo - u, hi - u + 1e-12)).x
        moved = False
        for lam in (1.0, 0.5, 0.25):
            un = np.clip(u + lam * step, lo, hi)
            fn = model.residual_vector(un)
            cn = float(fn @ fn)
            if cn < cost:
                u, f, cost, moved = un, fn, cn, True
                break
        if not moved or float(np.max(np.abs(lam * step))) < 1e-3:
            break
    return u, jac


def polish(model: _Model, u0: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_nfev: int,
           pattern_nfev: int = 0) -> np.ndarray:
    """Derivative-free refinement of the Gauss-Newton result: bounded Powell (Brent line searches along
    each parameter) on the weighted cost, inside a trust region around it (a factor 4.5 either way for
    log-scaled parameters; for linear ones one typical size or the distance from zero, whichever is
    larger). The simulated response is not smooth at small scales (stick-slip instants, encoder counts),
    which can stall the secant Gauss-Newton steps far from the minimum; line searches need no slope."""
    span = np.array([1.5 if p.scale == "log" else max(1.0, abs(float(x))) for p, x in zip(model.free, u0, strict=True)])
    lo_t = np.maximum(lo, u0 - span)
    hi_t = np.minimum(hi, u0 + span)
    if np.any(hi_t <= lo_t):
        return u0
    f0 = model.residual_vector(u0)
    c0 = float(f0 @ f0)

    def cost(u: np.ndarray) -> float:
        f = model.residual_vector(np.clip(u, lo_t, hi_t))
        return float(f @ f) / max(c0, 1e-300)

    res = optimize.minimize(cost, u0, method="Powell", bounds=list(zip(lo_t, hi_t, strict=True)),
                            options={"xtol": 0.01, "ftol": 1e-4, "maxfev": max_nfev})
    u = np.clip(res.x, lo_t, hi_t)
    u = u if cost(u) < 1.0 else u0
    if pattern_nfev > 0:
        u = pattern_search(cost, u, lo_t, hi_t, [1.0 if p.scale == "log" else max(abs(float(x)), 1.0)
                                                 for p, x in zip(model.free, u, strict=True)], pattern_nfev)
    return u


def pattern_search(cost: Callable[[np.ndarray], float], u0: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   scale: list[float], max_nfev: int, steps: tuple[float, ...] = (0.2, 0.07, 0.025)) -> np.ndarray:
    """Coarse-to-fine compass search: try +-step x scale along each parameter, move on improvement,
    refine the step when nothing improves. Brent's line searches assume one minimum per line; on a cost
    with roughness (chaotic stick-slip or count-edge detail) they can settle in a dip away from the broad
    basin, which the coarse steps see past."""
    u = u0.copy()
    c = cost(u)
    n = 0
    for step in steps:
        improved = True
        while improved and n < max_nfev:
            improved = False
            for j in range(u.size):
                for sgn in (1.0, -1.0):
                    if n >= max_nfev:
                        break
                    v = u.copy()
                    v[j] = min(max(v[j] + sgn * step * scale[j], lo[j]), hi[j])
                    if v[j] == u[j]:
                        continue
                    cv = cost(v)
                    n += 1
                    if cv < c:
                        u, c, improved = v, cv, True
                        break
    return u


#: a parameter direction counts as determined by the fit traces only when its response over one secant step
#: exceeds the model's chaos by this share of one chaos draw's energy: that energy varies by about 11 % (1 sd)
#: from draw to draw on the bench's ball-screw axis (6 draws each on the resonance and Stribeck cases; the chatter
#: is bursty, far from the sqrt(2 / n) of white noise), so 0.25 is above 2 sd of it
MIN_INFORMATION_OVER_CHAOS = 0.25
#: secant step (x the settings' step) tried for parameters the normal step leaves buried in the chaos
UNCERTAINTY_WIDE_STEP = 3.0


def chaos_corrected_covariance(jac: np.ndarray, steps: np.ndarray, chaos_sq: float | list[float], s2_eff: float,
                               min_over_chaos: float = MIN_INFORMATION_OVER_CHAOS,
                               segments: list[slice] | None = None) -> np.ndarray:
    """Parameter covariance of a least-squares fit whose model is chaotic, in the Jacobian's units.

    ``jac`` (m x k) holds secant columns ``(r(u + h_j e_j) - r(u)) / h_j`` (``steps`` = h). In a chaotic
    model every simulation at a new parameter value is a fresh draw of the model's own chatter, so each
    column carries, besides the parameter's real effect, the difference of two draws; ``chaos_sq`` is the
    energy of one such difference (two draws at the same parameters). In step units (columns ``jac h``) the
    expected chaos part of ``(J h)^T (J h)`` is ``c (I + 1 1^T)`` with ``c = chaos_sq / 2`` (all columns
    share the draw at ``u``); it is subtracted, and ``cov = s2_eff A^-1`` on the directions whose remaining
    information exceeds ``min_over_chaos * chaos_sq``. A parameter that loads on a direction below that is
    *not determined* by the data: its variance is ``inf``. ``s2_eff``: residual variance per decorrelated
    sample. Without chaos (``chaos_sq = 0``) this is ``s2_eff (J^T J)^-1``.

    ``segments``: the rows of each independently simulated trace, with ``chaos_sq`` then one energy per
    segment. A parameter the pooled test leaves undetermined is tested again trace by trace: each trace's
    information counts where it clears that trace's own chaos, and the cleared parts are summed. One short
    trace can pin a parameter that the chatter of the long ones would bury in the pooled sum (a rapid move
    ringing a mode that no sine excites)."""
    k = jac.shape[1]
    if k == 0:
        return np.zeros((0, 0))
    h = np.abs(np.asarray(steps, dtype=float))
    js = jac * h
    if segments is None:
        return _covariance_of_information(_significant_information(js, float(chaos_sq), min_over_chaos), h, s2_eff)
    per_segment = [float(c) for c in chaos_sq]  # type: ignore[union-attr]
    cov = chaos_corrected_covariance(jac, steps, sum(per_segment), s2_eff, min_over_chaos)
    if np.all(np.isfinite(np.diag(cov))) or len(segments) < 2:
        return cov
    kept = [_significant_information(js[rows], c, min_over_chaos) for rows, c in zip(segments, per_segment,
                                                                                      strict=True)]
    by_trace = _covariance_of_information(sum(kept), h, s2_eff)
    # a parameter counts only where one trace alone determines it (its loading on that trace's cleared
    # directions >= 0.9, the pooled test's rule): summing cleared directions of several traces would otherwise
    # lend a buried parameter the small, chaos-set components of other parameters' directions
    loading = np.max([np.diag(np.linalg.pinv(a, hermitian=True) @ a) for a in kept], axis=0)
    for j in range(k):
        if not math.isfinite(cov[j, j]) and loading[j] >= 0.9:
            cov[j, j] = by_trace[j, j]
    return cov


def _significant_information(js: np.ndarray, chaos_sq: float, min_over_chaos: float) -> np.ndarray:
    """``(J h)^T (J h)`` less its expected chaos part, on the directions above ``min_over_chaos * chaos_sq``
    only (zero elsewhere)."""
    k = js.shape[1]
    c = 0.5 * max(chaos_sq, 0.0)
    info = js.T @ js - c * (np.eye(k) + np.ones((k, k)))
    lam, vec = np.linalg.eigh(0.5 * (info + info.T))
    floor = max(min_over_chaos * 2.0 * c, 1e-12 * max(float(np.max(np.abs(lam))), 1e-300))
    ok = lam > floor
    return (vec[:, ok] * lam[ok]) @ vec[:, ok].T


def _covariance_of_information(info: np.ndarray, h: np.ndarray, s2_eff: float) -> np.ndarray:
    """``s2_eff info^-1`` in parameter units; ``inf`` variance for a parameter loading on its null space."""
    k = info.shape[0]
    lam, vec = np.linalg.eigh(0.5 * (info + info.T))
    ok = lam > 1e-10 * max(float(np.max(np.abs(lam))), 1e-300)
    cov_s = (vec[:, ok] / lam[ok]) @ vec[:, ok].T * s2_eff
    lost = np.sum(vec[:, ~ok] ** 2, axis=1)  # each parameter's loading on the undetermined directions
    var = np.diag(cov_s).copy()
    var[lost > 0.1] = math.inf
    cov = cov_s * np.outer(h, h)
    cov[np.diag_indices(k)] = var * h**2
    return cov


def fit_candidate(job: FitJob) -> CandidateResult:
    """Screen (stage "screen") or refine and judge on held-out data (stage "refine") one effect."""
    t0 = time.perf_counter()
    model = _Model(job)
    if job.stage == "screen":
        values, gain, _ = screen(job, model)
        alts = _alternative_starts(model, values, job.settings.alt_starts)
        return CandidateResult(job.effect, values, {}, {}, {}, {}, {}, float("nan"), model.n_sims,
                               time.perf_counter() - t0, stage="screen", screen_gain=gain, alternatives=alts)
    start = {**model.nominal_values(), **job.start}
    fixed0 = {k: v for k, v in start.items() if fx.is_discrete(k)}
    model.fixed = dict(fixed0)
    base = model.stack([job.base_preds[i] for i in job.fit_idx])
    model.size = base.size
    u0 = model.internal(start)
    lo, hi = model.bounds()
    # keep the start strictly inside the bounds for the trust-region method
    u0 = np.clip(u0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    jac = None
    fixed_hat = fixed0
    if job.settings.method == "de":
        res = optimize.differential_evolution(
            lambda u: float(np.sum(model.residual_vector(u) ** 2)), list(zip(lo, hi, strict=True)),
            x0=u0, maxiter=6, popsize=5, polish=False, seed=0, tol=1e-3,
        )
        u_hat = res.x
    elif job.settings.method == "lsq":
        res = optimize.least_squares(
            model.residual_vector, u0, jac=lambda u: model.secant_jacobian(u), bounds=(lo, hi), method="trf",
            x_scale=1.0, max_nfev=job.settings.max_nfev, xtol=1e-3, ftol=1e-3,
        )
        u_hat, jac = res.x, res.jac
    else:
        best_c = math.inf
        for k, st in enumerate([job.start, *job.alt_starts]):
            full = {**model.nominal_values(), **st}
            model.fixed = {key: v for key, v in full.items() if fx.is_discrete(key)}
            us = u0 if k == 0 else np.clip(model.internal(full), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
            u_k, jac_k = gauss_newton(model, us, lo, hi, job.settings.max_iter)
            if job.settings.polish_nfev > 0:
                u_pol = polish(model, u_k, lo, hi, job.settings.polish_nfev + 12 * (len(model.free) - 1),
                               job.settings.pattern_nfev * len(model.free))
                if not np.array_equal(u_pol, u_k):
                    u_k, jac_k = u_pol, None
            f_k = model.residual_vector(u_k)
            c_k = float(f_k @ f_k)
            if c_k < best_c:
                best_c, u_hat, jac, fixed_hat = c_k, u_k, jac_k, dict(model.fixed)
    model.fixed = dict(fixed0)
    r0 = model.residual_vector(u0)
    model.fixed = fixed_hat
    if float(r0 @ r0) < float(model.residual_vector(u_hat) @ model.residual_vector(u_hat)):
        u_hat, model.fixed = u0, dict(fixed0)  # never worse than the screening estimate
    values = model.values(u_hat)
    cfg_hat = model.cfg(u_hat)
    # uncertainty: cov = s^2 (J^T J)^-1, inflated by the residual correlation time (n / n_eff), with the part
    # of J^T J that is the model's own chaos taken out (see chaos_corrected_covariance)
    if jac is None:
        jac = model.secant_jacobian(u_hat)
    rvec = model.residual_vector(u_hat)
    m, k = rvec.size, len(model.free)
    s2 = float(rvec @ rvec) / max(m - k, 1)
    s2_eff = s2 / max(min(job.weights.n_eff_fraction.values(), default=1.0), 1e-6)
    chaos = model.chaos_difference(u_hat)
    rows = model.trace_rows
    if chaos is None or sum(r.stop - r.start for r in rows) != rvec.size:
        rows = [slice(0, rvec.size)]
    chaos_sq = [float(chaos[r] @ chaos[r]) if chaos is not None else 0.0 for r in rows]
    cov_u = chaos_corrected_covariance(jac, model.jacobian_steps(u_hat), chaos_sq, s2_eff, segments=rows)
    if not np.all(np.isfinite(np.diag(cov_u))):
        # buried in the chaos over one step: the response over a longer secant (its energy grows with the
        # step squared, the chaos's does not) may still determine it
        wide = UNCERTAINTY_WIDE_STEP
        cov_w = chaos_corrected_covariance(model.secant_jacobian(u_hat, wide), model.jacobian_steps(u_hat, wide),
                                           chaos_sq, s2_eff, segments=rows)
        for j in range(cov_u.shape[0]):
            if not math.isfinite(cov_u[j, j]) and math.isfinite(cov_w[j, j]):
                cov_u[j, j] = cov_w[j, j]
    stderr = {}
    su_int = []
    for j, p in enumerate(model.free):
        su = math.sqrt(max(cov_u[j, j], 0.0)) if math.isfinite(cov_u[j, j]) else math.inf
        su_int.append(su)
        dv = p.typical if p.scale == "lin" else values[p.name]
        stderr[p.name] = float(su * dv)
    at_bound = [p.name for p, x, a, b, su in zip(model.free, u_hat, lo, hi, su_int, strict=True)
                if _at_bound(p, x, a, b, su)]
    fit_pred = model.predict(cfg_hat, job.fit_idx)
    hold_pred = model.predict(cfg_hat, job.holdout_idx)
    fit_res = [residuals(job.traces[i], p) for i, p in zip(job.fit_idx, fit_pred, strict=True)]
    hold_res = [residuals(job.traces[i], p) for i, p in zip(job.holdout_idx, hold_pred, strict=True)]
    overlap = float("nan")
    if job.target is not None and job.target_channel:
        items = []
        for i, pa in zip(job.fit_idx + job.holdout_idx, fit_pred + hold_pred, strict=True):
            td, pb = job.traces[i], job.base_preds.get(i, {})
            ch = job.target_channel
            if ch in pa and ch in pb:
                items.append((td.name, td.t, td.pos_cmd, {ch: pa[ch] - pb[ch]}))
        if items:
            overlap = signature_overlap(localise(items, job.target.scale), job.target, job.target_channel)
    return CandidateResult(
        effect=job.effect, values=values, stderr=stderr,
        fit_ssr=weighted_ssr(fit_res, job.weights), holdout_ssr=weighted_ssr(hold_res, job.weights),
        fit_metrics=pooled_metrics(fit_res), holdout_metrics=pooled_metrics(hold_res) if hold_res else {},
        signature_overlap=overlap, n_sims=model.n_sims, seconds=time.perf_counter() - t0, at_bound=at_bound,
        stage="refine",
    )


def _at_bound(p: fx.Param, x: float, lo: float, hi: float, su: float) -> bool:
    """A fitted parameter (internal units ``x``, standard error ``su``) at a bound of its physical range: on it,
    or a bound other than a physical zero within one standard error (the data do not tell the value from the
    bound: a Stribeck velocity of 48 +- 3 mm/s under a 50 mm/s bound is the fit asking for more than the
    range allows, a Coulomb-like friction dressed as Stribeck)."""
    for b, bv in ((lo, p.lower), (hi, p.upper)):
        if abs(x - b) < 1e-6 * max(1, abs(b)):
            return True
        if bv != 0.0 and math.isfinite(su) and abs(x - b) < su:
            return True
    return False


def _safe_fit(job: FitJob) -> CandidateResult:
    try:
        return fit_candidate(job)
    except Exception as exc:  # one failing candidate must not sink the diagnosis
        return CandidateResult(job.effect, {}, {}, {}, {}, {}, {}, float("nan"), 0, 0.0,
                               error=f"{type(exc).__name__}: {exc}", stage=job.stage)


# ------------------------------------------------------------------------------------------- runners
class Runner:
    """Runs candidate fits: in-process (jobs=1), a local process pool, or a Dask cluster."""

    def __init__(self, jobs: int = 1, scheduler: str | None = None, connect_timeout_s: float = 10.0):
        self.jobs = max(1, int(jobs))
        self.scheduler = scheduler
        self._pool = None
        self._client = None
        if scheduler:
            try:
                from dask.distributed import Client
            except ImportError as exc:
                raise ImportError(
                    "--scheduler needs the optional dependency dask[distributed] "
                    "(pip install 'virtualaxis[dask]')"
                ) from exc
            try:
                self._client = Client(scheduler, timeout=connect_timeout_s)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ConnectionError(f"--scheduler {scheduler}: cannot use the Dask scheduler there "
                                      f"({type(exc).__name__}: {exc})") from None
        elif self.jobs > 1:
            import multiprocessing as mp

            ctx = mp.get_context("fork")
            self._worker_pids = ctx.Array("q", self.jobs)  # filled by each worker as it starts
            self._started = ctx.Value("i", 0)
            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=ctx, initializer=_worker_init,
                                             initargs=(self._worker_pids, self._started))

    def map(self, jobs: list[FitJob], progress: Callable[[CandidateResult], None] | None = None):
        results: list[CandidateResult] = []
        if self._client is not None:
            from dask.distributed import as_completed as dask_completed

            futs = [self._client.submit(_safe_fit, j, pure=False) for j in jobs]
            for f in dask_completed(futs):
                r = f.result()
                results.append(r)
                if progress:
                    progress(r)
        elif self._pool is not None:
            futs = [self._pool.submit(_safe_fit, j) for j in jobs]
            for f in as_completed(futs):
                r = f.result()
                results.append(r)
                if progress:
                    progress(r)
        else:
            for j in jobs:
                r = _safe_fit(j)
                results.append(r)
                if progress:
                    progress(r)
        order = {j.effect: k for k, j in enumerate(jobs)}
        return sorted(results, key=lambda r: order[r.effect])

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def abort(self) -> None:
        """End the pool at once (an interrupt, an error): queued fits are dropped and running ones killed, so that
        nothing waits for a fit that takes minutes (workers ignore SIGINT: the main process decides)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            me = os.getpid()
            with self._started.get_lock():
                pids = list(self._worker_pids[: self._started.value])
            for pid in pids:
                if _parent_of(pid) == me:  # (still our worker, not a process that reused its number)
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None


def _worker_init(pids, started) -> None:
    """In each pool worker: SIGINT ignored (a Ctrl-C reaches the whole process group; the main process ends the
    pool), the terminating signals the CLI turns into exceptions back to their default action, and the worker's
    process id recorded for :meth:`Runner.abort`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for name in ("SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGXCPU", "SIGVTALRM", "SIGPROF",
                 "SIGPWR", "SIGIO", "SIGSTKFLT"):
        sig = getattr(signal, name, None)
        if sig is not None and callable(signal.getsignal(sig)):
            signal.signal(sig, signal.SIG_DFL)
    with started.get_lock():
        if started.value < len(pids):
            pids[started.value] = os.getpid()
            started.value += 1


def _parent_of(pid: int) -> int | None:
    """The parent process id of ``pid`` (Linux /proc), None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            return int(fh.read().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None
