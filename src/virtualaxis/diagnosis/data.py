"""A data set of traces of one axis, the simulation on their commands, and residual metrics.

The nominal model is simulated on each trace's own command (and known external force) with the
sensor noise switched off (the expected response). Residuals are ``measured - simulated`` in every
channel both carry. Channel weights for fitting are ``1 / sigma_c`` with
``sigma_c = max(noise_c, 0.1 * rms_c, q_c / sqrt(12))``: the noise floor of the channel (from the
high-frequency part of its residual) but never less than a tenth of its baseline gap, so that every
channel with a real gap counts about equally and channels with only noise barely count, and never less
than the quantisation noise of a channel recorded on a grid of step ``q_c`` (an encoder count: a
residual of the size of one count is which side of a count edge the model lands on, not information), and
never less than the model's own chaos: how much its prediction changes under an unmeasurably small change
of the command (:func:`chaos_floor`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.diagnosis.recording import apply_post
from virtualaxis.diagnosis.trace import Trace

SimulateFn = Callable[..., dict]


def default_simulate(cfg: AxisConfig, t_s: np.ndarray, pos_cmd_m: np.ndarray, force_ext_n=None, seed: int = 0):
    """The project's batch simulator (imported lazily so the diagnosis imports without it)."""
    from virtualaxis.sim import simulate_command

    return simulate_command(cfg, t_s, pos_cmd_m, force_ext_n=force_ext_n, seed=seed)


def noiseless(cfg: AxisConfig) -> AxisConfig:
    """The expected response: sensor noise off (quantisation stays, it is deterministic)."""
    s = cfg.sensors
    if s.position_noise_m == 0 and s.current_noise_a == 0:
        return cfg
    return cfg.replace(sensors={"position_noise_m": 0.0, "current_noise_a": 0.0})


@dataclass
class TraceData:
    """What a fit worker needs of one trace (plain arrays: cheap to pickle)."""

    name: str
    t: np.ndarray
    pos_cmd: np.ndarray
    force_ext: np.ndarray | None
    measured: dict[str, np.ndarray]
    overrides: dict = field(default_factory=dict)  # config sections overridden for this trace
    post: dict = field(default_factory=dict)  # how the trace records the model's channels (recording.apply_post)

    @classmethod
    def from_trace(cls, tr: Trace, overrides: dict | None = None) -> TraceData:
        return cls(tr.name, tr.t, tr.pos_cmd, tr.force_ext, {c: tr.columns[c] for c in tr.channels()},
                   overrides or {})


#: standstill simulated before every trace (and cut off) [s]: a recorded axis has been enabled and settled before
#: the recording starts, while the simulator starts with the table on the command, the motor at command / r and
#: the spring relaxed without any kinematic offset. With a warm screw (thermal growth from the fixed bearing) or a
#: lead error that start is not at rest: the spring carries offset x stiffness (3.5 K on 0.45 m: 18 um, ~3 kN on
#: a 160 MN/m screw) and the loop rings for ~50 ms, which costs more in the force channels than the effect
#: explains. 0.2 s is 8 time constants of the slowest loop of a feed drive (Kv 40 1/s: 25 ms).
SETTLE_S = 0.2


def settled(simulate: SimulateFn, cfg: AxisConfig, t: np.ndarray, pos_cmd: np.ndarray,
            force_ext: np.ndarray | None, seed: int, settle_s: float = SETTLE_S) -> dict[str, np.ndarray]:
    """``simulate`` on ``t`` after ``settle_s`` of standstill at ``pos_cmd[0]`` (no external force); the
    outputs of the settling part are cut off, so every channel is on ``t`` again."""
    t = np.asarray(t, dtype=float)
    if t.size < 2 or settle_s <= 0:
        return simulate(cfg, t, pos_cmd, force_ext, seed)
    dt = float(t[1] - t[0])
    n = int(round(settle_s / dt))
    tt = np.concatenate([t[0] - dt * np.arange(n, 0, -1), t])
    pp = np.concatenate([np.full(n, float(pos_cmd[0])), pos_cmd])
    ff = None if force_ext is None else np.concatenate([np.zeros(n), force_ext])
    out = simulate(cfg, tt, pp, ff, seed)
    return {k: (np.asarray(v)[n:] if np.ndim(v) == 1 and np.size(v) == tt.size else v) for k, v in out.items()}


def simulate_trace(cfg: AxisConfig, td: TraceData, simulate: SimulateFn) -> dict[str, np.ndarray]:
    """Model prediction for the measured channels of one trace (after :data:`SETTLE_S` of standstill)."""
    c = cfg.replace(**td.overrides) if td.overrides else cfg
    out = settled(simulate, noiseless(c), td.t, td.pos_cmd, td.force_ext, 0)
    pred = {}
    for ch in td.measured:
        x = out.get(ch)
        if x is None and ch == "force_drive":
            x = drive_force_of_torque(c, out)
        if x is None:
            continue
        x = np.asarray(x, dtype=float)
        if x.shape == td.t.shape and np.isfinite(x).all():
            pred[ch] = x
    if td.post:
        pred = apply_post(td, pred, c.mechanics.lead_m)
    return pred


def drive_force_of_torque(cfg: AxisConfig, out: dict) -> np.ndarray | None:
    """A motor axis reports torque; a trace of it may carry the axial drive force instead (a controller that
    outputs force, torque expressed at the table): ``F = T 2 pi / lead`` (ideal screw). None for a force
    actuator or a direct drive."""
    if cfg.actuator.kind == "force" or cfg.mechanics.lead_m <= 0 or "torque_meas" not in out:
        return None
    return np.asarray(out["torque_meas"], dtype=float) * (2 * math.pi / cfg.mechanics.lead_m)


def residuals(td: TraceData, pred: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {ch: td.measured[ch] - pred[ch] for ch in pred}


def channel_metrics(r: np.ndarray) -> dict[str, float]:
    return {"rmse": float(np.sqrt(np.mean(r**2))), "mae": float(np.mean(np.abs(r))), "max": float(np.max(np.abs(r)))}


def pooled_metrics(res_list: list[dict[str, np.ndarray]]) -> dict[str, dict[str, float]]:
    """Per channel rmse / mae / max over several traces."""
    out: dict[str, dict[str, float]] = {}
    chans = sorted({c for r in res_list for c in r})
    for ch in chans:
        x = np.concatenate([r[ch] for r in res_list if ch in r])
        out[ch] = channel_metrics(x)
    return out


def noise_floor(r: np.ndarray) -> float:
    """White-noise sigma from second differences (robust, insensitive to a smooth gap)."""
    if r.size < 8:
        return 0.0
    d2 = np.diff(r, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def correlation_time(r: np.ndarray, max_lag: int = 2000) -> float:
    """Integrated autocorrelation time in samples (>= 1): n / tau independent samples."""
    x = r - r.mean()
    n = x.size
    if n < 16 or not np.any(x):
        return 1.0
    m = min(max_lag, n // 2)
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: m + 1]
    ac = ac / ac[0]
    neg = np.flatnonzero(ac <= 0)
    stop = int(neg[0]) if neg.size else m + 1
    return float(max(1.0, 1.0 + 2.0 * np.sum(ac[1:stop])))


def quantum(x: np.ndarray) -> float:
    """The step of a channel recorded on a grid (encoder counts, scale resolution, a fixed number of
    decimals), or 0.0 when its values are not on one: the smallest step between distinct values, kept
    only when (almost) every other step is an integer multiple of it."""
    u = np.unique(np.asarray(x, dtype=float)[np.isfinite(x)])
    if u.size < 3:
        return 0.0
    d = np.diff(u)
    q = float(d.min())
    if q <= 1e-12 * max(float(np.max(np.abs(u))), 1e-300):
        return 0.0
    k = d / q
    return q if float(np.quantile(np.abs(k - np.round(k)), 0.9)) < 0.02 else 0.0


@dataclass
class Weights:
    sigma: dict[str, float]
    n_eff_fraction: dict[str, float]  # n_eff / n per channel
    quantum: dict[str, float] = field(default_factory=dict)  # grid step of quantised channels
    chaos: dict[str, float] = field(default_factory=dict)  # non-reproducible part per channel (model's own)
    resolution: dict[str, float] = field(default_factory=dict)  # what the sensor resolves: sqrt(noise^2 + q^2/12)

    @classmethod
    def from_residuals(cls, res_list: list[dict[str, np.ndarray]],
                       quanta: dict[str, float] | None = None, chaos: dict[str, float] | None = None) -> Weights:
        """``quanta``: the grid step of quantised measured channels (see :func:`quantum`); ``chaos``: the
        rms the model's own prediction changes by under an unmeasurably small change of its command (see
        :func:`chaos_floor`)."""
        sigma, frac, resolution = {}, {}, {}
        quanta = dict(quanta or {})
        chaos = dict(chaos or {})
        chans = sorted({c for r in res_list for c in r})
        for ch in chans:
            rs = [r[ch] for r in res_list if ch in r]
            x = np.concatenate(rs)
            rms = float(np.sqrt(np.mean(x**2)))
            noise = float(np.median([noise_floor(r) for r in rs]))
            sigma[ch] = max(noise, 0.1 * rms, quanta.get(ch, 0.0) / math.sqrt(12.0), chaos.get(ch, 0.0), 1e-300)
            resolution[ch] = math.hypot(noise, quanta.get(ch, 0.0) / math.sqrt(12.0))
            taus = [correlation_time(r) for r in rs]
            frac[ch] = float(1.0 / max(np.mean(taus), 1.0))
        return cls(sigma, frac, {c: q for c, q in quanta.items() if c in sigma},
                   {c: x for c, x in chaos.items() if c in sigma}, resolution)

    def resolved_removal(self, before: dict[str, float], after: dict[str, float], counts: dict[str, int]
                         ) -> dict[str, float]:
        """Per channel, the rms a model change removes from the residual (weighted sums of squares ``before`` ->
        ``after`` over ``counts`` samples) in units of what the sensor resolves (:attr:`resolution`); channels
        without a resolution are left out."""
        out: dict[str, float] = {}
        for ch, b in before.items():
            res = self.resolution.get(ch, 0.0)
            if res <= 0 or ch not in after or not counts.get(ch):
                continue
            removed_ms = max(b - after[ch], 0.0) * self.sigma[ch] ** 2 / counts[ch]
            out[ch] = math.sqrt(removed_ms) / res
        return out


CHAOS_PERTURBATION_M = 1e-12  # white perturbation of the command for the chaos floor [m], far below any scale


def perturbed_command(td: TraceData, rng: np.random.Generator) -> TraceData:
    """The trace with its command moved by white noise of ``CHAOS_PERTURBATION_M`` (far below any scale):
    simulating it gives another draw of the model's chaos (see :func:`chaos_floor`)."""
    return TraceData(td.name, td.t, td.pos_cmd + rng.normal(0.0, CHAOS_PERTURBATION_M, td.t.size),
                     td.force_ext, td.measured, td.overrides, td.post)


def chaos_floor(cfg: AxisConfig, traces: list[TraceData], simulate: SimulateFn,
                preds: list[dict[str, np.ndarray]] | None = None, seed: int = 0) -> dict[str, float]:
    """Per channel, the rms by which the model's own prediction changes when its command changes by an
    unmeasurably small amount (white, ``CHAOS_PERTURBATION_M``).

    A quantised loop with stick-slip friction is chaotic: encoder counts and stick instants make the
    current chatter, and which chatter comes out depends on the least digit of the command. That part of
    any measured trace cannot be reproduced by any model, so it is a noise floor of the channel weights
    (bench, clean case: the residual of the exact model is 0.239 A rms in i_q; this floor is 0.242 A)."""
    rng = np.random.default_rng(seed)
    diffs: dict[str, list[np.ndarray]] = {}
    for k, td in enumerate(traces):
        base = preds[k] if preds is not None else simulate_trace(cfg, td, simulate)
        other = simulate_trace(cfg, perturbed_command(td, rng), simulate)
        for ch, x in other.items():
            if ch in base:
                diffs.setdefault(ch, []).append(x - base[ch])
    return {ch: float(np.sqrt(np.mean(np.concatenate(v) ** 2))) for ch, v in diffs.items()}


def channel_quanta(traces: list[TraceData]) -> dict[str, float]:
    """Grid step per measured channel over several traces (the largest seen; 0.0 = not quantised)."""
    out: dict[str, float] = {}
    for td in traces:
        for ch, x in td.measured.items():
            out[ch] = max(out.get(ch, 0.0), quantum(x))
    return out


def weighted_ssr(res_list: list[dict[str, np.ndarray]], w: Weights) -> dict[str, float]:
    """Per channel sum of squares in units of sigma_c."""
    out: dict[str, float] = {}
    for r in res_list:
        for ch, x in r.items():
            if ch in w.sigma:
                out[ch] = out.get(ch, 0.0) + float(np.sum((x / w.sigma[ch]) ** 2))
    return out


def sample_counts(res_list: list[dict[str, np.ndarray]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for r in res_list:
        for ch, x in r.items():
            out[ch] = out.get(ch, 0) + x.size
    return out


def info_criterion_delta(
    before: dict[str, float], after: dict[str, float], counts: dict[str, int], w: Weights, n_params: int
) -> float:
    """BIC difference (after - before) with effective (decorrelated) sample counts; < 0 pays its way."""
    delta = 0.0
    n_eff_total = 0.0
    for ch, b in before.items():
        a = after.get(ch, b)
        n_eff = max(1.0, counts[ch] * w.n_eff_fraction.get(ch, 1.0))
        n_eff_total += n_eff
        delta += n_eff * math.log(max(a, 1e-300) / max(b, 1e-300))
    return float(delta + n_params * math.log(max(n_eff_total, 2.0)))


def split_by_condition(traces: list[Trace]) -> tuple[list[int], list[int]]:
    """Fit on the slowest and the fastest trace, hold out the rest (seed 000's split). With fewer than
    three traces there is nothing to hold out in between: 2 -> fit the first, hold out the second."""
    n = len(traces)
    if n == 1:
        return [0], []
    if n == 2:
        return [0], [1]
    speeds = [t.max_speed_m_s() for t in traces]
    order = list(np.argsort(speeds, kind="stable"))
    fit = sorted({int(order[0]), int(order[-1])})
    return fit, [i for i in range(n) if i not in fit]
