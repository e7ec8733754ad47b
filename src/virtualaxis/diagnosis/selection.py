"""Choosing the unmodelled effects, round by round, as stages each returning a small typed result.

A round: :func:`prepare_round` (the current model's residual, where it lies, the hints) -> :func:`screen` (every
remaining candidate from its starts, one simulation each) -> :func:`refine` (the best screened, fitted) ->
:func:`judge` (each refined candidate scored on held-out data; ranked; parsimony) -> :func:`reduce_nested` (a
nested, simpler effect that explains the same) -> :func:`choose_pair` (two effects fitted jointly as one
candidate) -> :func:`refit_near` (a further effect judged with the earlier ones refitted together with it) ->
:func:`find_mismatch` (when nothing pays: a gap only an implausible candidate would explain) -> :func:`accept`
-> :func:`refit_accepted` (joint refit of all accepted effects, backward step).

A candidate pays its way when (1) the BIC with decorrelated sample counts falls on the held-out traces, (2) the
held-out weighted residual energy falls by at least ``min_gain`` and (3) the part of the residual its correction
explains lies where the gap lies (signature overlap). The best paying candidate is accepted, the model updated,
and the remaining candidates are fitted again on top of it, until none pays. Nothing accepted -> "no
significant effect". :func:`select_effects` drives the rounds.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.data import (
    SimulateFn,
    TraceData,
    Weights,
    channel_quanta,
    chaos_floor,
    info_criterion_delta,
    residuals,
    sample_counts,
    simulate_trace,
    weighted_ssr,
)
from virtualaxis.diagnosis.fit import CandidateResult, FitJob, FitSettings, Runner
from virtualaxis.diagnosis.progress import ProgressEvent, ProgressFn, item_counter
from virtualaxis.diagnosis.where import Localisation, MotionScale, localise

#: a candidate must remove from the held-out residual, in some channel, an rms of at least this many times what
#: the sensor resolves there (sqrt(noise^2 + quantum^2 / 12), ``Weights.resolution``)
MIN_RESOLVED_REMOVAL = 1.0
#: candidates of a round (the best held out) whose pairs are fitted jointly as one candidate
PAIR_TOP = 3
#: joint refit passes after an acceptance (each from the previous pass's values)
JOINT_PASSES = 3
# effects that change the same config keys cannot both be accepted
_SAME_KEYS = {
    frozenset({"coulomb_friction", "friction_asymmetry"}),
}


# ------------------------------------------------------------------------------------------- typed results
class JudgedOn(str, Enum):
    """What a candidate's gain was measured on."""

    HOLDOUT = "holdout"
    FIT = "fit"
    SCREENING = "screening"  # screened only: not refined, not judged


@dataclass(frozen=True)
class Score:
    """How much of the residual one candidate explains, and the figures that decide whether it pays its way."""

    judged_on: JudgedOn
    gain: float = 0.0  # share of the weighted residual energy removed (held out, else on the fit traces)
    fit_gain: float = 0.0  # ... on the fit traces
    ic_delta: float = math.inf  # information-criterion change (< 0: worth its parameters)
    gain_per_channel: dict[str, float] = field(default_factory=dict)
    gain_of_nominal: float = 0.0  # gain x the share of the nominal gap left before the round
    worst_channel_gain: float = 0.0
    relative_change: float | None = None  # how far its values move the model (None: the effect was absent)
    removed_over_resolution: dict[str, float] = field(default_factory=dict)
    resolved: bool = True  # removes at least MIN_RESOLVED_REMOVAL sensor resolutions in some channel
    implausible: tuple[str, ...] = ()  # why its values are no answer (empty: they are)
    gain_over_single: float | None = None  # a pair: its gain over the best single candidate's
    joint_gain: float | None = None  # refitted jointly with the earlier effects (refit_near)
    joint_gain_of_nominal: float | None = None
    joint_worst_channel_gain: float | None = None


@dataclass(frozen=True)
class Judged:
    """One candidate of a round: its fit, its score and the decision."""

    result: CandidateResult
    score: Score
    pays: bool
    explains: bool = False  # pays but for its plausibility
    signature_ok: bool = True
    screen_gain: float = 0.0
    small_alone: bool = False  # pays but for what the earlier effects' held values may cost (refit_near decides)
    chosen_because: str = ""  # parsimony, a pair or a joint refit put it first
    fitted_alone: dict | None = None  # a pair's part: its own single fit of the round

    @property
    def effect(self) -> str:
        return self.result.effect


@dataclass(frozen=True)
class Step:
    """One accepted effect and the cumulative state after it."""

    effect: str
    values: dict[str, float]
    stderr: dict[str, float]
    cfg: AxisConfig
    fit_metrics: dict
    holdout_metrics: dict


@dataclass(frozen=True)
class SelectionProblem:
    """What every round works on."""

    cfg: AxisConfig  # the nominal model
    traces: list[TraceData]
    fit_idx: list[int]
    holdout_idx: list[int]
    simulate: SimulateFn
    settings: FitSettings
    scale: MotionScale
    hint_fn: Callable[[AxisConfig, list[dict]], dict] | None = None

    @property
    def all_idx(self) -> list[int]:
        return self.fit_idx + self.holdout_idx


@dataclass(frozen=True)
class RoundContext:
    """The model before a round and its residual: what every candidate of the round is judged against."""

    round: int  # 1-based
    cfg: AxisConfig
    preds: dict[int, dict]
    weights: Weights
    before_fit: dict[str, float]
    before_hold: dict[str, float]
    counts_fit: dict[str, int]
    counts_hold: dict[str, int]
    left: float  # share of the nominal gap left before the round
    target_channel: str  # the channel that carries most of the weighted gap
    target: Localisation  # where the residual lies
    hints: dict
    n_sims: int  # simulations this preparation ran


@dataclass(frozen=True)
class Screening:
    ordered: tuple[CandidateResult, ...]  # best screening gain first
    n_sims: int


@dataclass(frozen=True)
class Refinement:
    by_effect: dict[str, CandidateResult]
    n_sims: int


@dataclass(frozen=True)
class Judgement:
    """The round's candidates, ranked (paying first, by information criterion)."""

    scored: tuple[Judged, ...]
    n_sims: int = 0

    @property
    def best(self) -> Judged | None:
        return self.scored[0] if self.scored and self.scored[0].pays else None


@dataclass(frozen=True)
class PairChoice:
    """Two effects fitted jointly that beat the best single one: their steps and one round entry each."""

    steps: tuple[Step, ...]
    rounds: tuple[tuple[Judged, ...], tuple[Judged, ...]]
    n_sims: int


@dataclass(frozen=True)
class NearRefit:
    """A further effect, too small alone, accepted with the earlier ones refitted jointly with it."""

    judged: Judged
    steps: tuple[Step, ...]
    joint: dict | None  # the joint refit's figures when its values were kept
    n_sims: int


@dataclass(frozen=True)
class Refit:
    """After an acceptance: all accepted effects refitted jointly, then the backward step."""

    accepted: tuple[Step, ...]
    joint: dict | None
    removed: tuple[dict, ...]
    n_sims: int


@dataclass(frozen=True)
class Selection:
    rounds: list[list[Judged]]  # per round, each candidate's scores
    accepted: list[Step]
    skipped: dict[str, str]
    final_cfg: AxisConfig
    seconds_fitting: float
    n_sims: int
    joint: dict | None = None  # the joint refit of the accepted effects (see joint_refit)
    weights: Weights | None = None  # the channel weights every cost of the selection used
    removed: list[dict] = field(default_factory=list)  # effects dropped again by a backward step
    mismatch: dict | None = None  # the gap a library effect would explain only with implausible parameters
    trail: list[dict] = field(default_factory=list)  # per round, what each stage did (report.json "stages")


# ------------------------------------------------------------------------------------------- scoring
def score(cand: CandidateResult, before_fit: dict, before_hold: dict, counts_fit: dict, counts_hold: dict,
          w: Weights, n_params: int) -> Score:
    """Held-out gain and information-criterion change of one candidate."""
    use_hold = bool(before_hold)
    on = JudgedOn.HOLDOUT if use_hold else JudgedOn.FIT
    b, a, cnt = (before_hold, cand.holdout_ssr, counts_hold) if use_hold else (before_fit, cand.fit_ssr, counts_fit)
    if cand.error or not a:
        return Score(on)
    tot_b = sum(b.values())
    tot_a = sum(a.get(ch, v) for ch, v in b.items())
    gain = 1.0 - tot_a / max(tot_b, 1e-300)
    fit_gain = 1.0 - sum(cand.fit_ssr.get(ch, v) for ch, v in before_fit.items()) / max(sum(before_fit.values()),
                                                                                         1e-300)
    per_ch = {ch: 1.0 - a.get(ch, v) / max(v, 1e-300) for ch, v in b.items()}
    return Score(on, gain=float(gain), fit_gain=float(fit_gain), gain_per_channel=per_ch,
                 ic_delta=info_criterion_delta(b, a, cnt, w, n_params))


def n_free(effect: str, cfg: AxisConfig) -> int:
    """Number of fitted (not discrete) parameters of an effect: what the information criterion counts."""
    return len([p for p in fx.effect_of(effect).params(cfg) if not fx.is_discrete(p.name)])


def judge_one(r: CandidateResult, screen_gain: float, ctx: RoundContext, settings: FitSettings) -> Judged:
    """Score one refined candidate and decide whether it pays its way (see the module docstring)."""
    cur = ctx.cfg
    s = score(r, ctx.before_fit, ctx.before_hold, ctx.counts_fit, ctx.counts_hold, ctx.weights, n_free(r.effect, cur))
    sig_ok = not (r.signature_overlap < settings.min_signature_overlap)
    gain_of_nominal = s.gain * ctx.left
    worst = min(s.gain_per_channel.values(), default=0.0)
    change = fx.relative_change(r.effect, cur, r.values) if r.values else 0.0
    # what the candidate removes, in units of what the sensors resolve: a gain below one sensor resolution in
    # every channel is a fit to quantisation and noise, however large a share of a small residual it is
    hold = bool(ctx.before_hold)
    removal = ctx.weights.resolved_removal(ctx.before_hold if hold else ctx.before_fit,
                                           (r.holdout_ssr if hold else r.fit_ssr) or {},
                                           ctx.counts_hold if hold else ctx.counts_fit)
    resolved = not removal or max(removal.values()) >= MIN_RESOLVED_REMOVAL
    explains = (resolved and change >= fx.MIN_RELATIVE_CHANGE and s.ic_delta < 0 and s.gain >= settings.min_gain
                and gain_of_nominal >= settings.min_gain_total and worst >= settings.max_channel_loss
                and sig_ok and not r.error)
    why_not = fx.implausible(r.effect, cur, r.values, r.stderr, r.at_bound) if r.values and not r.error else []
    s = dataclasses.replace(s, gain_of_nominal=gain_of_nominal, worst_channel_gain=worst,
                            relative_change=change if math.isfinite(change) else None,  # None: JSON-safe
                            removed_over_resolution=removal, resolved=resolved, implausible=tuple(why_not))
    pays = explains and not why_not
    # everything but what the earlier effects, held at values fitted without it (and biased by it), may cost: its
    # share of the nominal gap, or a channel the biased earlier values now over-correct; the joint refit decides
    # (refit_near)
    small = (not pays and not why_not and not r.error and sig_ok and resolved and change >= fx.MIN_RELATIVE_CHANGE
             and s.ic_delta < 0 and s.gain >= settings.min_gain
             and (gain_of_nominal < settings.min_gain_total or worst < settings.max_channel_loss))
    return Judged(r, s, pays, explains=explains, signature_ok=sig_ok, screen_gain=screen_gain, small_alone=small)


def _rank_key(d: Judged) -> tuple:
    return (not d.pays, d.score.ic_delta, -d.screen_gain)


def _to_front(scored: list[Judged], d: Judged, old: Judged | None = None) -> list[Judged]:
    """``d`` first; ``old`` (or ``d`` itself when it is in the list) taken out."""
    rest = [x for x in scored if x is not d and x is not old]
    return [d, *rest]


# ------------------------------------------------------------------------------------------- stages of a round
def selection_weights(problem: SelectionProblem, cur: AxisConfig, preds: dict[int, dict], res: dict[int, dict]
                      ) -> tuple[Weights, int]:
    """Channel weights from the nominal residual, kept for all rounds (comparable costs); and simulations run."""
    fit = problem.fit_idx
    chaos = chaos_floor(cur, [problem.traces[i] for i in fit], problem.simulate, [preds[i] for i in fit])
    w = Weights.from_residuals([res[i] for i in fit], channel_quanta([problem.traces[i] for i in problem.all_idx]),
                               chaos)
    return w, len(fit)


def prepare_round(problem: SelectionProblem, rnd: int, cur: AxisConfig, w: Weights | None, nominal_hold: float
                  ) -> RoundContext:
    """The current model simulated on every trace, its residual weighted and located, the fit's hints."""
    all_idx, fit_idx, hold_idx, tr = problem.all_idx, problem.fit_idx, problem.holdout_idx, problem.traces
    preds = {i: simulate_trace(cur, tr[i], problem.simulate) for i in all_idx}
    n_sims = len(all_idx)
    res = {i: residuals(tr[i], preds[i]) for i in all_idx}
    if w is None:
        w, k = selection_weights(problem, cur, preds, res)
        n_sims += k
    before_fit = weighted_ssr([res[i] for i in fit_idx], w)
    before_hold = weighted_ssr([res[i] for i in hold_idx], w)
    now = sum((before_hold or weighted_ssr([res[i] for i in fit_idx], w)).values())
    left = now / max(nominal_hold if rnd > 1 else now, 1e-300)
    counts_fit = sample_counts([res[i] for i in fit_idx])
    counts_hold = sample_counts([res[i] for i in hold_idx])
    target_ch = max(before_fit, key=lambda c: before_fit[c] / max(counts_fit[c], 1)) if before_fit else ""
    target = localise([(tr[i].name, tr[i].t, tr[i].pos_cmd, res[i]) for i in all_idx], problem.scale)
    hints = problem.hint_fn(cur, [res[i] for i in all_idx]) if problem.hint_fn else {}
    hints.setdefault("peaks_hz", spectral_peaks(target, target_ch))
    hints.setdefault("peaks_all_hz", [f for ch in sorted(target.spectra) if ch != target_ch
                                      for f in spectral_peaks(target, ch)[:2]])
    return RoundContext(rnd, cur, preds, w, before_fit, before_hold, counts_fit, counts_hold, left, target_ch, target,
                        hints, n_sims)


def _job_args(problem: SelectionProblem, ctx: RoundContext) -> dict:
    return dict(cfg=ctx.cfg, traces=problem.traces, fit_idx=problem.fit_idx, holdout_idx=problem.holdout_idx,
                weights=ctx.weights, hints=ctx.hints, settings=problem.settings, simulate=problem.simulate,
                base_preds=ctx.preds, target=ctx.target, target_channel=ctx.target_channel)


def screen(problem: SelectionProblem, ctx: RoundContext, remaining: list[str], runner: Runner,
           progress: ProgressFn | None = None) -> Screening:
    """Every remaining candidate from its starting values, one simulation each; best screening gain first."""
    if progress:
        progress(ProgressEvent("screen", round=ctx.round, total=len(remaining)))
    screened = runner.map([FitJob(n, stage="screen", **_job_args(problem, ctx)) for n in remaining],
                          progress=item_counter(progress, "screen", ctx.round, len(remaining)))
    return Screening(tuple(sorted(screened, key=lambda r: -r.screen_gain)), sum(r.n_sims for r in screened))


def refine(problem: SelectionProblem, ctx: RoundContext, screening: Screening, runner: Runner,
           progress: ProgressFn | None = None) -> Refinement:
    """The ``refine_top`` screened candidates that explain at least ``min_screen_gain`` of the fit residual,
    fitted from their best starts."""
    settings = problem.settings
    top = [r for r in screening.ordered if r.screen_gain >= settings.min_screen_gain and not r.error]
    top = top[: settings.refine_top]
    if progress:
        progress(ProgressEvent("refine", round=ctx.round, total=len(top)))
    refined = runner.map([FitJob(r.effect, stage="refine", start=r.values, alt_starts=r.alternatives,
                                 **_job_args(problem, ctx)) for r in top],
                         progress=item_counter(progress, "refine", ctx.round, len(top)))
    by = {r.effect: dataclasses.replace(r, screen_gain=r0.screen_gain) for r0 in top for r in refined
          if r.effect == r0.effect}
    return Refinement(by, sum(r.n_sims for r in refined))


def judge(ctx: RoundContext, screening: Screening, refinement: Refinement, settings: FitSettings) -> Judgement:
    """Each refined candidate scored against the round's residual (a screened-only one: not judged), ranked
    paying first by information criterion, then parsimony."""
    scored: list[Judged] = []
    for r0 in screening.ordered:
        r = refinement.by_effect.get(r0.effect)
        if r is None:
            scored.append(Judged(r0, Score(JudgedOn.SCREENING, fit_gain=r0.screen_gain), False,
                                 screen_gain=r0.screen_gain))
        else:
            scored.append(judge_one(r, r0.screen_gain, ctx, settings))
    scored.sort(key=_rank_key)
    return Judgement(tuple(parsimony(scored, ctx.cfg, settings.parsimony)))


def parsimony(scored: list[Judged], cur: AxisConfig, tolerance: float, absolute: float = 0.01) -> list[Judged]:
    """Among paying candidates, move a simpler one (fewer parameters) to the front when it leaves at
    most ``tolerance`` more held-out residual energy than the best, or at most ``absolute`` (a share of
    the energy before this round) more: nested effects such as Coulomb friction inside friction
    asymmetry must not win by a parameter that buys nothing (a 110.4 / 109.2 N "asymmetry" that leaves
    3.3 % instead of 3.9 % of the energy is Coulomb friction)."""
    paying = [d for d in scored if d.pays]
    if len(paying) < 2:
        return list(scored)

    def k(d: Judged) -> int:
        return n_free(d.effect, cur)

    best = paying[0]
    left_best = 1.0 - best.score.gain
    simpler = [d for d in paying[1:] if k(d) < k(best)
               and 1.0 - d.score.gain <= (1 + tolerance) * left_best + absolute]
    if not simpler:
        return list(scored)
    choice = min(simpler, key=lambda d: (k(d), d.score.ic_delta))
    chosen = dataclasses.replace(choice, chosen_because=f"preferred over {best.effect} (fewer parameters, as good "
                                                        "held out)")
    return _to_front(scored, chosen, choice)


def reduce_nested(problem: SelectionProblem, ctx: RoundContext, judgement: Judgement, remaining: list[str],
                  runner: Runner) -> Judgement:
    """A paying nested effect whose extra parameters buy nothing (viscous asymmetry whose two directions agree)
    -> the simpler one, refitted from its values, when it pays its way too."""
    best = judgement.best
    if best is None:
        return judgement
    r = best.result
    red = fx.reduce_nested(r.effect, r.values, r.stderr)
    if red is None or red[0] not in remaining:
        return judgement
    simple = runner.map([FitJob(red[0], stage="refine", start=red[1], **_job_args(problem, ctx))])[0]
    old = next((d for d in judgement.scored if d.effect == red[0]), None)
    d = judge_one(simple, old.screen_gain if old else 0.0, ctx, problem.settings)
    if not d.pays:
        return Judgement(judgement.scored, judgement.n_sims + simple.n_sims)
    d = dataclasses.replace(d, chosen_because=f"preferred over {r.effect}: its fitted values agree within their "
                                              "uncertainty, the nested effect explains the same")
    rest = [x for x in judgement.scored if x is not old]
    return Judgement((d, *rest), judgement.n_sims + simple.n_sims)


def _shares_parameters(a: str, b: str, cfg: AxisConfig) -> bool:
    """True when two effects set a parameter of the same name (viscous friction inside viscous asymmetry)."""
    return bool({p.name for p in fx.EFFECTS[a].params(cfg)} & {p.name for p in fx.EFFECTS[b].params(cfg)})


def choose_pair(problem: SelectionProblem, ctx: RoundContext, judgement: Judgement, accepted: list[Step],
                runner: Runner) -> PairChoice | None:
    """Two effects fitted jointly as one candidate, when that pays its way and beats the best single effect.

    Forward selection adds one effect at a time: the first one fitted alone absorbs what a second mechanism of
    a similar signature does (Coulomb friction fitted alone on an axis with Coulomb and viscous friction takes
    the viscous force at the traces' speeds: 1.8x the Coulomb value), and the second, judged on top of that
    biased first, then explains too little. So the :data:`PAIR_TOP` refined candidates that explain most held
    out are also fitted in pairs (from their single values). A pair wins when it pays its way like a single
    candidate, each of its effects is plausible and changes the model (judged on its part of the joint values),
    and it leaves at most ``1 - min_gain`` of the held-out energy the best paying single candidate leaves with
    a lower information criterion (the second effect pays its way on top)."""
    cur, best, common = ctx.cfg, judgement.best, _job_args(problem, ctx)
    fitted = [d for d in judgement.scored if d.result.stage == "refine" and not d.result.error and d.result.values
              and d.score.gain > 0 and d.score.judged_on != JudgedOn.SCREENING]
    fitted.sort(key=lambda d: -d.score.gain)
    top = fitted[:PAIR_TOP]
    jobs = []
    for i, a in enumerate(top):
        for b in top[i + 1:]:
            ea, eb = a.effect, b.effect
            if conflicts(ea, eb) or _shares_parameters(ea, eb, cur):
                continue
            start = {f"{e}{fx.JOINT_SEP}{k}": v for e, d in ((ea, a), (eb, b)) for k, v in d.result.values.items()}
            jobs.append(FitJob(f"{ea}+{eb}", stage="refine", start=start, **common))
    if not jobs:
        return None
    found = None
    for r in runner.map(jobs):
        d = judge_pair(r, best, ctx, problem.settings)
        if d is not None and d.pays and (found is None or d.score.ic_delta < found.score.ic_delta):
            found = d
    if found is None:
        return None
    # a part that reduces to a nested, simpler effect (viscous asymmetry whose two directions agree is viscous
    # friction): the pair with the simpler one, refitted, is preferred when it pays its way too
    r = found.result
    parts, errs = fx.split_joint(r.values), fx.split_joint(r.stderr)
    reduced = {e: fx.reduce_nested(e, v, errs.get(e, {})) for e, v in parts.items()}
    if any(x is not None and x[0] != e for e, x in reduced.items()):
        start = {}
        for e, v in parts.items():
            name, vals = (e, v) if reduced[e] is None or reduced[e][0] == e else reduced[e]
            start.update({f"{name}{fx.JOINT_SEP}{k}": x for k, x in vals.items()})
        names = "+".join(dict.fromkeys(k.partition(fx.JOINT_SEP)[0] for k in start))
        simple = judge_pair(runner.map([FitJob(names, stage="refine", start=start, **common)])[0], best, ctx,
                            problem.settings)
        if simple is not None and simple.pays:
            found = dataclasses.replace(
                simple, result=dataclasses.replace(simple.result, n_sims=simple.result.n_sims + r.n_sims),
                chosen_because=f"preferred over {r.effect}: its nested part's fitted values agree within their "
                               "uncertainty")
    steps, rounds = pair_steps(cur, found, judgement.scored)
    names = {s.effect for s in steps}
    first = tuple(rounds[0]) + tuple(d for d in judgement.scored if d.effect not in names)
    return PairChoice(tuple(accepted) + tuple(steps), (first, tuple(rounds[1])), found.result.n_sims)


def judge_pair(r: CandidateResult, best: Judged | None, ctx: RoundContext, settings: FitSettings) -> Judged | None:
    """Judge a jointly fitted pair (see :func:`choose_pair`); None for a failed fit."""
    cur = ctx.cfg
    if r.error or not r.values:
        return None
    d = judge_one(r, 0.0, ctx, settings)
    parts = fx.split_joint(r.values)
    errs = fx.split_joint(r.stderr)
    at_bound = fx.split_joint_names(r.at_bound)
    why = [f"{e}: {w}" for e, v in parts.items()
           for w in fx.implausible(e, cur, v, errs.get(e, {}), at_bound.get(e, []))]
    why += [f"{e} changes the model by only {100 * fx.relative_change(e, cur, v):.1f} %"
            for e, v in parts.items() if fx.relative_change(e, cur, v) < fx.MIN_RELATIVE_CHANGE]
    s = dataclasses.replace(d.score, implausible=d.score.implausible + tuple(why))
    pays = d.pays and not why
    if best is not None:
        left_single = 1.0 - best.score.gain
        left_pair = 1.0 - s.gain
        s = dataclasses.replace(s, gain_over_single=1.0 - left_pair / max(left_single, 1e-300))
        pays = pays and left_pair <= (1.0 - settings.min_gain) * left_single and s.ic_delta < best.score.ic_delta
    return dataclasses.replace(d, score=s, pays=pays)


def pair_steps(cur: AxisConfig, pair: Judged, scored: tuple[Judged, ...]) -> tuple[list[Step], list[list[Judged]]]:
    """The two steps of an accepted pair and one round entry per effect (the report lists each effect with its
    part of the joint values and the pair's figures; ``fitted_alone``: its own single fit of the round)."""
    r = pair.result
    alone = {d.effect: {"values": d.result.values, "heldout_gain": d.score.gain} for d in scored}
    values, errs = fx.split_joint(r.values), fx.split_joint(r.stderr)
    at_bound = fx.split_joint_names(r.at_bound)
    steps, rounds = [], []
    c = cur
    for e, v in values.items():
        c = fx.EFFECTS[e].apply(c, v)
        steps.append(Step(e, v, errs.get(e, {}), c, r.fit_metrics, r.holdout_metrics))
        part = dataclasses.replace(r, effect=e, values=v, stderr=errs.get(e, {}),
                                   at_bound=at_bound.get(e, []))
        rounds.append([dataclasses.replace(
            pair, result=part, pays=True, fitted_alone=alone.get(e),
            chosen_because=f"accepted with {', '.join(x for x in values if x != e)}: {r.effect} fitted jointly")])
    return steps, rounds


def refit_near(problem: SelectionProblem, ctx: RoundContext, judgement: Judgement, accepted: list[Step],
               runner: Runner, progress: ProgressFn | None = None) -> NearRefit | None:
    """A further effect judged with the earlier ones refitted together with it: forward selection holds them at
    values fitted without it (Coulomb friction 22.8 N absorbing a withheld viscous friction on the reference's
    rigid axis, truth 20 N + 200 N s/m; viscous alone on top explained 1.9 % of the nominal gap, the pair
    refitted jointly 3x that; backlash on top of a Coulomb friction fitted 12 % high without it made the held-out
    torque 30 % worse). The best candidate that pays but for its share of the nominal gap or a channel made worse
    is accepted when, refitted jointly, it removes ``min_gain`` of the round's energy and ``min_gain_total`` of
    the nominal's and leaves no channel worse than ``max_channel_loss``."""
    settings = problem.settings
    near = [d for d in judgement.scored if d.small_alone]
    if not near:
        return None
    d = min(near, key=lambda d: d.score.ic_delta)
    r = d.result
    cur = ctx.cfg
    trial = accepted + [Step(r.effect, r.values, r.stderr, fx.EFFECTS[r.effect].apply(cur, r.values),
                             r.fit_metrics, r.holdout_metrics)]
    if progress:
        progress(ProgressEvent("joint_refit", round=ctx.round, effects=tuple(s.effect for s in trial)))
    jr = joint_refit(problem.cfg, trial, problem.traces, problem.fit_idx, problem.holdout_idx, ctx.weights, settings,
                     problem.simulate, runner)
    n_sims = jr.pop("n_sims")
    steps = jr.pop("steps")
    before = sum((ctx.before_hold or ctx.before_fit).values())
    after = jr["heldout_cost_joint" if problem.holdout_idx else "fit_cost_joint"] if jr["accepted"] else \
        sum((r.holdout_ssr if problem.holdout_idx else r.fit_ssr).values())
    g = 1.0 - after / max(before, 1e-300)
    per_ch = (jr["heldout_ssr_joint" if problem.holdout_idx else "fit_ssr_joint"] if jr["accepted"] else
              (r.holdout_ssr if problem.holdout_idx else r.fit_ssr))
    worst = min((1.0 - per_ch.get(ch, v) / max(v, 1e-300) for ch, v in (ctx.before_hold or ctx.before_fit).items()),
                default=0.0)
    d = dataclasses.replace(d, score=dataclasses.replace(d.score, joint_gain=g, joint_gain_of_nominal=g * ctx.left,
                                                         joint_worst_channel_gain=worst))
    if not (g >= settings.min_gain and g * ctx.left >= settings.min_gain_total and worst >= settings.max_channel_loss):
        return NearRefit(d, (), None, n_sims)
    d = dataclasses.replace(d, pays=True, chosen_because="accepted after a joint refit with the earlier effects")
    return NearRefit(d, tuple(steps if jr["accepted"] else trial), jr, n_sims)


def find_mismatch(ctx: RoundContext, judgement: Judgement, settings: FitSettings
                  ) -> tuple[Judgement, dict | None]:
    """Nothing pays: a candidate that would explain the gap but whose parameters are not physical or not
    determined is not an answer, nor one that would explain it but makes some channel clearly worse where the
    model cannot follow (the reference's 60 N load: force residual 60 -> 14 N, the motor encoder 2 -> 7 counts
    at breakaway); the gap is then a model-form mismatch none of the library's effects describes. Returns the
    round's candidates (the channel losses written into their scores) and the mismatch (None: none)."""
    expl = [d for d in judgement.scored if d.explains and d.score.implausible]
    scored: list[Judged] = []
    for d in judgement.scored:
        sc = d.score
        if (not d.explains and not sc.implausible and not d.result.error and sc.resolved and d.signature_ok
                and sc.ic_delta < 0 and sc.gain >= settings.min_gain and sc.gain_of_nominal >= settings.min_gain_total
                and sc.worst_channel_gain < settings.max_channel_loss):
            worse = [f"{ch} {100 * -g:.0f} % more residual energy held out"
                     for ch, g in sc.gain_per_channel.items() if g < settings.max_channel_loss]
            d = dataclasses.replace(d, score=dataclasses.replace(sc, implausible=(f"makes {', '.join(worse)}",)))
            expl.append(d)
        scored.append(d)
    out = Judgement(tuple(scored), judgement.n_sims)
    if not expl:
        return out, None
    d = min(expl, key=lambda d: d.score.ic_delta)
    tc = ctx.target_channel
    return out, {"round": ctx.round, "closest_effect": d.effect, "values": d.result.values,
                 "why_not": list(d.score.implausible), "heldout_gain": d.score.gain, "target_channel": tc,
                 "where": [{"channel": tc, "dimension": e["dimension"], "bin": e["bin"], "share": e["share"],
                            "concentration": e["share"] / max(e["time_fraction"], 1e-12)}
                           for e in ctx.target.concentrations(tc)[:5]] if tc else []}


def accept(cur: AxisConfig, accepted: list[Step], best: Judged, joint_steps: tuple[Step, ...] | None
           ) -> list[Step]:
    """The accepted steps after this round: the pair's or the joint refit's, else the best effect on top."""
    if joint_steps is not None:
        return list(joint_steps)
    r = best.result
    return accepted + [Step(r.effect, r.values, r.stderr, fx.EFFECTS[r.effect].apply(cur, r.values),
                            r.fit_metrics, r.holdout_metrics)]


def refit_accepted(problem: SelectionProblem, ctx: RoundContext, accepted: list[Step], runner: Runner,
                   progress: ProgressFn | None = None) -> Refit:
    """All accepted effects refitted together after an acceptance (effects that trade off leave the first one
    biased when it is held fixed), again from the joint values while a pass cuts the fit cost by 10 %; then
    each is tried without (:func:`backward_step`)."""
    if progress:
        progress(ProgressEvent("joint_refit", round=ctx.round, effects=tuple(s.effect for s in accepted)))
    n_sims = 0
    first = None
    at_bound: dict[str, list[str]] = {}  # of the joint values in use: effect -> parameters at a bound
    for _ in range(JOINT_PASSES):
        joint = joint_refit(problem.cfg, accepted, problem.traces, problem.fit_idx, problem.holdout_idx, ctx.weights,
                            problem.settings, problem.simulate, runner)
        n_sims += joint.pop("n_sims")
        steps = joint.pop("steps")
        if first is None:
            first = joint
        else:
            first.update({k: joint[k] for k in ("accepted", "joint_values", "joint_stderr", "fit_cost_joint",
                                                "heldout_cost_joint") if joint["accepted"]})
        if not joint["accepted"]:
            break
        accepted = steps
        at_bound = fx.split_joint_names(joint["at_bound"])
        if joint["fit_cost_joint"] > 0.9 * joint["fit_cost_sequential"]:
            break
    kept, dropped, k_sims = backward_step(problem.cfg, accepted, problem.traces, problem.fit_idx,
                                          problem.holdout_idx, ctx.weights, problem.settings, problem.simulate,
                                          at_bound)
    return Refit(tuple(kept), first, tuple({"round": ctx.round, **d} for d in dropped), n_sims + k_sims)


# ------------------------------------------------------------------------------------------- the driver
def select_effects(
    cfg: AxisConfig,
    traces: list[TraceData],
    fit_idx: list[int],
    holdout_idx: list[int],
    simulate: SimulateFn,
    runner: Runner,
    settings: FitSettings | None = None,
    effect_names: list[str] | None = None,
    progress: ProgressFn | None = None,
    weights: Weights | None = None,
    hint_fn: Callable[[AxisConfig, list[dict]], dict] | None = None,
) -> Selection:
    """Forward selection in rounds of the stages of this module, until no candidate pays its way."""
    settings = settings or FitSettings()
    cands, skipped = fx.applicable_effects(cfg, effect_names)
    problem = SelectionProblem(cfg, traces, fit_idx, holdout_idx, simulate, settings,
                               MotionScale.from_commands([(traces[i].t, traces[i].pos_cmd)
                                                          for i in fit_idx + holdout_idx]), hint_fn)
    remaining = [e.name for e in cands]
    cur, w = cfg, weights
    accepted: list[Step] = []
    rounds: list[list[Judged]] = []
    removed: list[dict] = []
    joint: dict | None = None
    mismatch: dict | None = None
    first_gain: dict[str, float] = {}
    trail: list[dict] = []
    nominal_hold = 0.0
    t0 = time.perf_counter()
    n_sims = 0
    for rnd in range(1, settings.max_rounds + 1):
        if not remaining:
            break
        ctx = prepare_round(problem, rnd, cur, w, nominal_hold)
        n_sims += ctx.n_sims
        w = ctx.weights
        if rnd == 1:
            nominal_hold = sum((ctx.before_hold or ctx.before_fit).values())
        else:  # only candidates that explained something on their own are tried on top
            remaining = [n for n in remaining if first_gain.get(n, 0.0) > settings.min_screen_gain / 3]
            if not remaining:
                break
        screening = screen(problem, ctx, remaining, runner, progress)
        n_sims += screening.n_sims
        if rnd == 1:
            first_gain = {r.effect: r.screen_gain for r in screening.ordered}
        trail.append({"stage": "screen", "round": rnd, "target_channel": ctx.target_channel,
                      "candidates": {r.effect: r.screen_gain for r in screening.ordered}})
        refinement = refine(problem, ctx, screening, runner, progress)
        n_sims += refinement.n_sims
        trail.append({"stage": "refine", "round": rnd, "refined": list(refinement.by_effect)})
        judgement = reduce_nested(problem, ctx, judge(ctx, screening, refinement, settings), remaining, runner)
        n_sims += judgement.n_sims
        best = judgement.best
        trail.append({"stage": "judge", "round": rnd, "paying": [d.effect for d in judgement.scored if d.pays],
                      "best": best.effect if best else None,
                      "chosen_because": best.chosen_because if best else ""})
        joint_steps: tuple[Step, ...] | None = None
        pair = choose_pair(problem, ctx, judgement, accepted, runner)
        if pair is not None:
            n_sims += pair.n_sims
            best, joint_steps = pair.rounds[0][0], pair.steps
            trail.append({"stage": "pair", "round": rnd, "accepted": [d[0].effect for d in pair.rounds],
                          "beats": judgement.best.effect if judgement.best else None})
            rounds.extend([list(pair.rounds[0]), list(pair.rounds[1])])
        elif best is None and accepted and settings.joint_refit:
            near = refit_near(problem, ctx, judgement, accepted, runner, progress)
            if near is not None:
                n_sims += near.n_sims
                trail.append({"stage": "joint_refit", "round": rnd, "effect": near.judged.effect,
                              "joint_gain": near.judged.score.joint_gain, "kept": near.judged.pays})
                others = [d for d in judgement.scored if d.effect != near.judged.effect]
                if near.judged.pays:
                    best, joint_steps, joint = near.judged, near.steps, near.joint
                    judgement = Judgement((near.judged, *others))
                else:
                    judgement = Judgement(tuple(near.judged if d.effect == near.judged.effect else d
                                                for d in judgement.scored))
        if best is None:
            judgement, mismatch = find_mismatch(ctx, judgement, settings)
            trail.append({"stage": "model_form", "round": rnd,
                          "mismatch": mismatch["closest_effect"] if mismatch else None})
        if pair is None:
            rounds.append(list(judgement.scored))
        if best is None:
            break
        accepted = accept(cur, accepted, best, joint_steps)
        cur = accepted[-1].cfg
        taken = {best.effect} | ({s.effect for s in joint_steps} if joint_steps is not None else set())
        remaining = [n for n in remaining if n not in taken and not any(conflicts(n, t) for t in taken)]
        if len(accepted) >= 2 and settings.joint_refit:
            refit = refit_accepted(problem, ctx, accepted, runner, progress)
            n_sims += refit.n_sims
            trail.append({"stage": "refit", "round": rnd, "effects": [s.effect for s in accepted],
                          "joint_values_kept": bool(refit.joint and refit.joint["accepted"]),
                          "removed": [d["effect"] for d in refit.removed]})
            accepted, joint = list(refit.accepted), refit.joint
            cur = accepted[-1].cfg if accepted else cfg
            if refit.removed:
                removed.extend(refit.removed)
                names = {d["effect"] for d in refit.removed}
                remaining = [n for n in remaining if n not in names]  # not tried again
    return Selection(rounds, accepted, skipped, cur, time.perf_counter() - t0, n_sims, joint, w, removed, mismatch,
                     trail)


# ------------------------------------------------------------------------------------------- refits
def _rebuild(cfg: AxisConfig, steps: list[Step]) -> list[Step]:
    """The steps' configs rebuilt from ``cfg`` (after one was removed)."""
    out, c = [], cfg
    for s in steps:
        c = fx.EFFECTS[s.effect].apply(c, s.values)
        out.append(Step(s.effect, s.values, s.stderr, c, s.fit_metrics, s.holdout_metrics))
    return out


def backward_step(cfg: AxisConfig, accepted: list[Step], traces: list[TraceData], fit_idx: list[int],
                  holdout_idx: list[int], w: Weights, settings: FitSettings, simulate: SimulateFn,
                  at_bound: dict[str, list[str]] | None = None) -> tuple[list[Step], list[dict], int]:
    """Try removing each accepted effect (the others kept at their values): one that no longer pays its way —
    the held-out weighted energy without it rises by less than ``min_gain`` of what the full model leaves, or
    the information criterion does not rise — is dropped (an early pick that a later, better effect explains).
    ``at_bound``: the parameters of each effect that the joint refit left at a bound of their range (effect ->
    names); such an effect is dropped too, by the rule every candidate is judged by (a value within one standard
    error of its bound is no answer, wherever the joint refit moved it). Returns (kept steps, dropped effects with
    their figures, simulations run)."""
    idx = holdout_idx or fit_idx
    n_sims = 0

    def energy(c: AxisConfig) -> tuple[float, dict, dict]:
        nonlocal n_sims
        res = [residuals(traces[i], simulate_trace(c, traces[i], simulate)) for i in idx]
        n_sims += len(idx)
        ssr = weighted_ssr(res, w)
        return sum(ssr.values()), ssr, sample_counts(res)

    dropped: list[dict] = []
    # an effect whose jointly refitted values no longer differ from the model's (by MIN_RELATIVE_CHANGE and
    # MIN_SIGNIFICANCE standard errors) was standing in for a bias of another effect's sequential fit
    for s in list(accepted):
        change = fx.relative_change(s.effect, cfg, s.values)
        why = [w_ for w_ in fx.implausible(s.effect, cfg, s.values, s.stderr, (at_bound or {}).get(s.effect, []))
               if "standard errors" in w_ or "at the bound" in w_]
        if len(accepted) >= 2 and (change < fx.MIN_RELATIVE_CHANGE or why):
            k = accepted.index(s)
            dropped.append({"effect": s.effect, "values": s.values, "heldout_energy_rise_without": math.nan,
                            "ic_delta_of_keeping": math.nan,
                            "why": why[0] if why else f"changes the model by only {100 * change:.1f} %"})
            accepted = _rebuild(cfg, accepted[:k] + accepted[k + 1:])
    changed = True
    while changed and len(accepted) >= 2:
        changed = False
        full, ssr_full, counts = energy(accepted[-1].cfg)
        worst = None
        for k, s in enumerate(accepted):
            rest = _rebuild(cfg, accepted[:k] + accepted[k + 1:])
            without, ssr_wo, _ = energy(rest[-1].cfg)
            rise = (without - full) / max(full, 1e-300)
            ic = info_criterion_delta(ssr_wo, ssr_full, counts, w, n_free(s.effect, cfg))  # adding it back
            if rise < settings.min_gain or ic >= 0:
                if worst is None or rise < worst[1]:
                    worst = (k, rise, ic, rest)
        if worst is not None:
            k, rise, ic, rest = worst
            dropped.append({"effect": accepted[k].effect, "values": accepted[k].values,
                            "heldout_energy_rise_without": rise, "ic_delta_of_keeping": ic,
                            "why": f"without it the held-out residual energy rises by only {100 * rise:.1f} %"})
            accepted = rest
            changed = True
    return accepted, dropped, n_sims


def joint_refit(cfg: AxisConfig, accepted: list[Step], traces: list[TraceData], fit_idx: list[int],
                holdout_idx: list[int], w: Weights, settings: FitSettings, simulate: SimulateFn,
                runner: Runner) -> dict:
    """Refit the parameters of all accepted effects together, from their forward-selection values.

    Forward selection fits each effect on top of the ones before it, with those held fixed; effects
    that trade off (backlash and compliance both lose motion at a reversal, mass and viscous friction
    both need force on a sine) leave the first one biased. The joint values replace the sequential
    ones when they lower the fit cost without raising the held-out cost."""
    all_idx = fit_idx + holdout_idx
    cur = accepted[-1].cfg
    preds = {i: simulate_trace(cur, traces[i], simulate) for i in all_idx}
    res = {i: residuals(traces[i], preds[i]) for i in all_idx}
    seq_fit = sum(weighted_ssr([res[i] for i in fit_idx], w).values())
    seq_hold = sum(weighted_ssr([res[i] for i in holdout_idx], w).values()) if holdout_idx else float("nan")
    name = "+".join(s.effect for s in accepted)
    start = {f"{s.effect}{fx.JOINT_SEP}{k}": v for s in accepted for k, v in s.values.items()}
    job = FitJob(name, cfg, traces, fit_idx, holdout_idx, w, {}, settings, simulate, stage="refine",
                 base_preds=preds, start=start)
    r = runner.map([job])[0]
    joint_fit = sum(r.fit_ssr.values()) if r.fit_ssr else math.inf
    joint_hold = sum(r.holdout_ssr.values()) if r.holdout_ssr else math.inf
    better = (not r.error and joint_fit < seq_fit
              and (not holdout_idx or joint_hold <= seq_hold))
    values, stderr = fx.split_joint(r.values), fx.split_joint(r.stderr)
    steps: list[Step] = []
    c = cfg
    for s in accepted:
        v = values.get(s.effect, s.values)
        c = fx.EFFECTS[s.effect].apply(c, v)
        steps.append(Step(s.effect, v, stderr.get(s.effect, s.stderr), c, r.fit_metrics, r.holdout_metrics))
    return {
        "effects": [s.effect for s in accepted],
        "accepted": bool(better),
        "sequential_values": {s.effect: s.values for s in accepted},
        "joint_values": values,
        "joint_stderr": stderr,
        "fit_cost_sequential": seq_fit, "fit_cost_joint": joint_fit,
        "heldout_cost_sequential": seq_hold, "heldout_cost_joint": joint_hold,
        "fit_ssr_joint": dict(r.fit_ssr or {}), "heldout_ssr_joint": dict(r.holdout_ssr or {}),
        "error": r.error, "seconds": r.seconds, "n_sims": r.n_sims, "steps": steps,
        "at_bound": list(r.at_bound),  # ("effect" + JOINT_SEP + "param") at a bound of its range
    }


def conflicts(a: str, b: str) -> bool:
    """Two effects that change the same config keys (cannot both be accepted)."""
    return frozenset({a, b}) in _SAME_KEYS


def spectral_peaks(loc: Localisation, channel: str) -> list[float]:
    """The strongest peaks (3..400 Hz) of a channel's residual spectrum, strongest first."""
    sp = loc.spectra.get(channel)
    if not sp:
        return []
    f = np.asarray(sp["f_hz"])
    p = np.asarray(sp["psd"])
    m = (f > 3.0) & (f < 400.0)
    if not m.any():
        return []
    f, p = f[m], p[m]
    idx = [i for i in range(1, len(p) - 1) if p[i] >= p[i - 1] and p[i] >= p[i + 1]]
    idx.sort(key=lambda i: -p[i])
    return [float(f[i]) for i in idx[:3]]
