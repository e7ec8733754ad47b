"""The whole diagnosis as stages, each a function returning a small typed result: load -> check -> baseline ->
localise -> select (:mod:`virtualaxis.diagnosis.selection`: screen, refine, judge, refit per round) -> verify ->
hybrid -> report. :func:`run_diagnosis` runs them and returns a :class:`DiagnosisResult`."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from virtualaxis.config import AxisConfig, ControlParams
from virtualaxis.config.errors import ConfigError, InputError
from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis import friction_law
from virtualaxis.diagnosis.alignment import apply_post, find_alignment, find_start_transient
from virtualaxis.diagnosis.contour import contour_report
from virtualaxis.diagnosis.controller import check_controller
from virtualaxis.diagnosis.data import (
    SimulateFn,
    TraceData,
    default_simulate,
    pooled_metrics,
    residuals,
    sample_counts,
    simulate_trace,
    split_by_condition,
)
from virtualaxis.diagnosis.fit import FitSettings, Runner
from virtualaxis.diagnosis.hybrid import fit_hybrid
from virtualaxis.diagnosis.plausibility import check_baseline
from virtualaxis.diagnosis.progress import ProgressEvent, ProgressFn
from virtualaxis.diagnosis.report import Plots, write_report
from virtualaxis.diagnosis.selection import Selection, select_effects
from virtualaxis.diagnosis.trace import CHANNEL_UNITS, Trace, check_units, read_trace
from virtualaxis.diagnosis.verdict import channel_verdict
from virtualaxis.diagnosis.where import Localisation, localise

NO_EFFECT = "no significant effect"
#: the conclusion when no library effect is accepted but a learned residual model removes most of a position
#: channel's held-out residual: the gap is systematic (predictable from the command and the measured state), and
#: not noise
UNEXPLAINED_GAP = "unexplained systematic gap"
#: a learned model that leaves at most this share of a position channel's held-out RMSE shows a systematic gap
SYSTEMATIC_GAP_RATIO = 0.3
_CONTROL_KEYS = {f.name for f in dataclasses.fields(ControlParams)}


def load_traces(cfg: AxisConfig, fit_paths: list[str], holdout_paths: list[str]) -> tuple[list[Trace], list[int],
                                                                                              list[int], list[str]]:
    """Read and check all traces; decide the fit / held-out split."""
    notes: list[str] = []
    traces = [read_trace(p, cfg.axis.name) for p in list(fit_paths) + list(holdout_paths)]
    for tr in traces:
        check_units(tr, cfg)
    check_sidecar_controllers(cfg, traces)
    from virtualaxis.diagnosis.plausibility import check_plausibility  # bad-input checks
    notes.extend(check_plausibility(cfg, traces, list(fit_paths), list(holdout_paths or [])))
    dts = {round(tr.dt_s, 12) for tr in traces}
    if len(dts) > 1:
        notes.append(f"traces have different sample periods {sorted(dts)} s; each is simulated on its own grid")
    names = [tr.name for tr in traces]
    for i, n in enumerate(names):
        if n in names[:i]:
            traces[i].name = f"{n}#{i}"
    if holdout_paths:
        fit_idx = list(range(len(fit_paths)))
        hold_idx = list(range(len(fit_paths), len(traces)))
    else:
        fit_idx, hold_idx = split_by_condition(traces)
        if hold_idx:
            notes.append(
                "no --holdout given: fitting on " + ", ".join(traces[i].name for i in fit_idx)
                + " (slowest and fastest), holding out " + ", ".join(traces[i].name for i in hold_idx)
            )
        else:
            notes.append("a single trace: no held-out data, candidates are judged on the fit trace (with the "
                         "information-criterion penalty only)")
    return traces, fit_idx, hold_idx, notes


def _sidecar_control(tr: Trace) -> tuple[dict, list[str]]:
    """The sidecar's ``[controller]`` table as (``control.*`` values by key, keys that are not ``control.*`` keys).
    A key may be written plain (``kv_per_min = 40``), dotted and quoted (``"control.kv_per_min" = 40``) or in a
    ``[controller.control]`` table; one key twice, or a ``controller`` that is not a table, is refused naming the
    sidecar."""
    ctrl = tr.metadata.get("controller")
    side = str(Path(tr.path).with_suffix(".toml"))
    if ctrl is None:
        return {}, []
    if not isinstance(ctrl, dict):
        raise InputError(side, f"controller: must be a table of control.* keys, [controller] (got {ctrl!r})")
    items: list[tuple[str, str, object]] = []  # (control key, as written, value)
    for k, v in ctrl.items():
        if k == "control" and isinstance(v, dict):
            items += [(kk, f"control.{kk}", vv) for kk, vv in v.items()]
        elif k.startswith("control."):
            items.append((k.removeprefix("control."), k, v))
        else:
            items.append((k, k, v))
    known: dict = {}
    unknown: list[str] = []
    for key, written, value in items:
        if key not in _CONTROL_KEYS:
            unknown.append(written)
        elif key in known:
            raise InputError(side, f"[controller] {written}: control.{key} given twice")
        else:
            known[key] = value
    return known, unknown


def check_sidecar_controllers(cfg: AxisConfig, traces: list[Trace]) -> None:
    """Each sidecar ``[controller]``'s ``control.*`` values are checked as the config's would be (type, range,
    consistency), and an error names the sidecar, not the axis config."""
    for tr in traces:
        known, _ = _sidecar_control(tr)
        if not known:
            continue
        try:
            cfg.replace(control=known)
        except ConfigError as exc:
            key = f"{exc.key}: " if exc.key else ""
            raise InputError(str(Path(tr.path).with_suffix(".toml")), f"[controller] {key}{exc.message}") from None


def trace_overrides(tr: Trace) -> dict:
    """Config overrides from the sidecar: a ``[controller]`` table with ``control.*`` keys (the gains of a
    controller that is not the config's; checked by :func:`check_sidecar_controllers`)."""
    known, unknown = _sidecar_control(tr)
    if unknown:
        tr.warnings.append(f"sidecar [controller] keys not used (not keys of the config's [control] section): "
                           f"{', '.join(unknown)}; the controller check compares the trace with the config's "
                           "control law instead")
    if known:
        tr.warnings.append(f"sidecar [controller] overrides control.{', control.'.join(known)} for this trace")
    return {"control": known} if known else {}


#: closed-loop judgement of an identified controller: the nominal model simulated with it must leave at most this
#: share of the RMSE the config's controller leaves (geometric mean over channels), on the fit traces (the config's
#: controller "fails" there) and again on the held-out traces (it does clearly better where it was not identified)
CLOSED_LOOP_RATIO = 0.7
#: ... and in at least one channel at most this share: a controller difference sets the following error, so it
#: shows as a large, clear change of the position channel, where a plant effect leaves a partial one (a 125 us
#: PI speed loop judged from 1 ms samples: the identified law cut the position residual only to 0.44-0.48 of the
#: config's on the independent reference's clean two-mass axis, whose controller is the config's; a P/P cascade
#: where the config says P/PI, with a withheld Coulomb friction dominating the force channel: 0.34)
CLOSED_LOOP_BEST_CHANNEL = 0.4
#: the fit traces' identified laws are one controller only when each gain agrees within this factor across them
#: (chosen: the identification's jackknife scatter on the bench traces is a few per cent; an independent model's
#: 2 ms position-feedback delay gave Kv 49.5 .. 156 1/s on four traces: a delay, not a controller)
CONTROLLER_AGREEMENT = 1.5


def check_controllers(cfg: AxisConfig, traces: list[Trace], tds: list[TraceData], simulate: SimulateFn,
                      fit_idx: list[int] | None = None, hold_idx: list[int] | None = None) -> list[dict]:
    """Replay the config's (or the sidecar's) control law on every trace with a controller output
    (:mod:`virtualaxis.diagnosis.controller`), then judge the controller closed-loop.

    The replay at the trace's rate is only a hint: a speed loop much faster than the trace (the normal case for
    a drive: a PI loop at 125 us recorded at 1 kHz) cannot be replayed from the samples, and a plant effect
    the replay does not see can make any law look wrong. So the config's control law is kept unless the nominal
    model simulated closed-loop with the identified law (the median of the fit traces' identified gains, or the
    speed-loop timing alone) leaves at most :data:`CLOSED_LOOP_RATIO` of the config's residual on the fit traces
    (the config's controller fails there) AND again on the held-out traces with no channel worse beyond its
    noise. Then it is used for every trace without a sidecar controller. Returns
    ``report.json["controller_check"]``; the decision is in each entry's ``used`` and ``closed_loop``."""
    fit_idx = list(range(len(traces))) if fit_idx is None else fit_idx
    hold_idx = hold_idx or []
    out: list[dict] = []
    checks: dict[int, object] = {}
    for k, (tr, td) in enumerate(zip(traces, tds, strict=True)):
        c0 = cfg.replace(**td.overrides) if td.overrides else cfg
        try:
            chk = check_controller(c0, tr.name, tr.t, tr.pos_cmd, tr.columns)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:  # a check, not a reason to stop
            tr.warnings.append(f"controller check skipped: {exc}")
            continue
        if chk is None:
            continue
        checks[k] = chk
    own = [k for k in checks if not tds[k].overrides.get("control")]  # no sidecar controller
    cand = [k for k in own if checks[k].used == "identified"]
    cand_fit = [k for k in cand if k in fit_idx] or cand
    judgement: dict = {}
    disagree = _disagreeing_gain([checks[k].overrides["control"] for k in cand_fit])
    if disagree:  # not one controller: what makes the config's law look wrong is not a control law
        for k in own:
            chk = checks[k]
            if chk.used == "identified" or k in cand:
                chk.used = "config"
                chk.overrides = {}
                chk.note = _kept(f"the fit traces' identified laws disagree ({disagree}), so they are not one "
                                 "controller", chk.note)
        judgement = {"used": False, "disagree": disagree}
        cand_fit = []
    if cand_fit:
        control = _median_overrides([checks[k].overrides["control"] for k in cand_fit])
        targets = [k for k in range(len(tds)) if not tds[k].overrides.get("control")]
        trial = {k: dataclasses.replace(tds[k], overrides={**tds[k].overrides, "control": control}) for k in targets}
        f_idx = [k for k in fit_idx if k in trial]
        h_idx = [k for k in hold_idx if k in trial]
        try:
            r_fit, v_fit = _closed_loop_ratio(cfg, [tds[k] for k in f_idx], [trial[k] for k in f_idx], simulate)
            r_hold, v_hold = (_closed_loop_ratio(cfg, [tds[k] for k in h_idx], [trial[k] for k in h_idx], simulate)
                              if h_idx else (math.nan, {}))
        except (ConfigError, ValueError, ArithmeticError) as exc:  # identified gains the schema or simulator refuse
            r_fit, v_fit, r_hold, v_hold = math.inf, {"error": str(exc)}, math.inf, {"error": str(exc)}
        def clear(r: float, v: dict) -> bool:
            best = min((c["ratio"] for c in v.get("channels", {}).values()), default=math.inf)
            return r <= CLOSED_LOOP_RATIO and best <= CLOSED_LOOP_BEST_CHANNEL and not v.get("worse_channels")

        fails = clear(r_fit, v_fit)
        better = clear(r_hold, v_hold) if h_idx else fails
        use = fails and better
        judgement = {"control": control, "ratio_fit": r_fit, "ratio_heldout": r_hold, "used": use,
                     "verdict_fit": v_fit, "verdict_heldout": v_hold}
        if use:
            for k in targets:
                tds[k].overrides = trial[k].overrides
        why = (f"closed loop, the nominal model with the identified controller leaves {r_fit:.2f} x the config "
               f"controller's residual on the fit traces" + (f" and {r_hold:.2f} x held out" if h_idx else ""))
        for k in own:
            chk = checks[k]
            chk.confirm_ratio = r_fit
            if use:
                chk.used = "identified"
                chk.overrides = {"control": control}
                chk.note = (chk.note + "; " if chk.note else "") + f"identified controller used: {why}"
            elif chk.used == "identified" or k in cand:
                chk.used = "config"
                chk.note = _kept(f"{why} (needs <= {CLOSED_LOOP_RATIO}, one channel <= {CLOSED_LOOP_BEST_CHANNEL} and "
                                 "none worse, on both)", chk.note)
    for k, chk in checks.items():
        if chk.note:
            traces[k].warnings.append(chk.note)
        d = chk.as_dict()
        if judgement:
            d["closed_loop"] = {key: v for key, v in judgement.items() if key != "control"}
        out.append(d)
    return out


#: the speed feed-forward forms a drive may derive from its position set-points (``control.velocity_ff_form``)
FEEDFORWARD_FORMS = ("derivative", "setpoint_difference")


def check_feedforward_form(cfg: AxisConfig, tds: list[TraceData], simulate: SimulateFn, fit_idx: list[int],
                           hold_idx: list[int]) -> dict | None:
    """Which form of the speed feed-forward the axis' drive uses: the command's derivative at the set-point's
    instant (our simulator's default) or the difference of consecutive set-points held for the next position
    cycle (a CiA 402 CSP drive deriving its velocity offset from the set-points: about half a cycle later).

    A controller-discretisation convention, not a plant effect, and one without any fitted freedom: the nominal
    model is simulated closed-loop with each form, and another form than the config's is used for every trace
    when it leaves at most :data:`CLOSED_LOOP_RATIO` of the config form's RMSE (geometric mean over channels)
    and at most :data:`CLOSED_LOOP_BEST_CHANNEL` in some channel, on the fit traces AND on the held-out traces
    (the same "clear controller difference" rule as for an identified control law). The lag of the
    feed-forward sets an acceleration-proportional following error, so the position channel shows it clearly
    even when a withheld plant effect is present; no channel-loss veto, because a plant effect (an encoder dead
    time) may have been cancelled in part by the wrong form. Returns ``report.json["feedforward_form"]``
    (None when the axis runs without speed feed-forward or the config has no such key)."""
    ctrl = cfg.control
    if getattr(ctrl, "velocity_ff_form", None) is None or ctrl.velocity_ff_factor <= 0:
        return None
    own = ctrl.velocity_ff_form
    out: dict = {"config_form": own, "used": own, "trials": {}}
    for form in FEEDFORWARD_FORMS:
        if form == own:
            continue
        trial = [dataclasses.replace(td, overrides=_merge_control(td.overrides, {"velocity_ff_form": form}))
                 for td in tds]
        try:
            r_fit, v_fit = _closed_loop_ratio(cfg, [tds[k] for k in fit_idx], [trial[k] for k in fit_idx], simulate)
            r_hold, v_hold = (_closed_loop_ratio(cfg, [tds[k] for k in hold_idx], [trial[k] for k in hold_idx],
                                                 simulate) if hold_idx else (r_fit, v_fit))
        except (ConfigError, ValueError, ArithmeticError) as exc:
            out["trials"][form] = {"error": str(exc)}
            continue

        def clear(r: float, v: dict) -> bool:
            best = min((c["ratio"] for c in v.get("channels", {}).values()), default=math.inf)
            return r <= CLOSED_LOOP_RATIO and best <= CLOSED_LOOP_BEST_CHANNEL

        use = clear(r_fit, v_fit) and clear(r_hold, v_hold)
        out["trials"][form] = {"ratio_fit": r_fit, "ratio_heldout": r_hold, "used": use,
                               "verdict_fit": v_fit, "verdict_heldout": v_hold}
        if use:
            for td, tt in zip(tds, trial, strict=True):
                td.overrides = tt.overrides
            out["used"] = form
            break
    out["note"] = (f"speed feed-forward form: {out['used']} (config: {own})" if out["used"] == own else
                   f"speed feed-forward form {out['used']} used instead of the config's {own}: closed loop the "
                   f"nominal model leaves {out['trials'][out['used']]['ratio_fit']:.2f} x the residual on the fit "
                   f"traces and {out['trials'][out['used']]['ratio_heldout']:.2f} x held out (a controller "
                   "convention, not a plant effect; calibrated.toml gets it)")
    return out


def _merge_control(overrides: dict, control: dict) -> dict:
    """``overrides`` with ``control`` keys added to (not replacing) its ``control`` section."""
    return {**overrides, "control": {**overrides.get("control", {}), **control}}


def _disagreeing_gain(ovs: list[dict], factor: float = CONTROLLER_AGREEMENT) -> str:
    """The first ``control.*`` key on which several traces' identified laws disagree beyond ``factor`` (or mix 0
    and non-0, e.g. P and PI), as "key lo .. hi"; "" when they agree or fewer than two are given."""
    if len(ovs) < 2:
        return ""
    for key in sorted(set().union(*ovs)):
        vals = [float(o[key]) for o in ovs if key in o]
        if len(vals) < 2:
            continue
        lo, hi = min(vals), max(vals)
        if (lo == 0.0) != (hi == 0.0) or (lo > 0.0 and hi / lo > CONTROLLER_AGREEMENT):
            return f"{key} {lo:.3g} .. {hi:.3g}"
    return ""


def _median_overrides(ovs: list[dict]) -> dict:
    """One controller from several traces' identified ``control.*`` overrides: the most common key set, each
    key's median."""
    sets: dict[tuple, list[dict]] = {}
    for o in ovs:
        sets.setdefault(tuple(sorted(o)), []).append(o)
    group = max(sets.values(), key=len)
    return {key: float(np.median([float(o[key]) for o in group])) for key in group[0]}


def _closed_loop_ratio(cfg: AxisConfig, a: list[TraceData], b: list[TraceData], simulate: SimulateFn
                       ) -> tuple[float, dict]:
    """Nominal model simulated closed-loop on traces ``a`` (config's controller) and ``b`` (same traces, other
    controller): geometric mean over channels of pooled rmse(b) / rmse(a), and the per-channel verdict."""
    if not a:
        return math.nan, {}
    ra = [residuals(td, simulate_trace(cfg, td, simulate)) for td in a]
    rb = [residuals(td, simulate_trace(cfg, td, simulate)) for td in b]
    ma, mb = pooled_metrics(ra), pooled_metrics(rb)
    chans = [c for c in ma if c in mb]
    if len(chans) > 1:
        chans = [c for c in chans if c != "motor_pos"]  # its zero is arbitrary until aligned
    logs = [math.log(mb[c]["rmse"] / ma[c]["rmse"]) for c in chans if ma[c]["rmse"] > 0 and mb[c]["rmse"] > 0]
    n_eff = {c: float(n) / 20.0 for c, n in sample_counts(ra).items()}  # ~20-sample correlation of a residual
    verdict = channel_verdict({c: ma[c]["rmse"] for c in chans}, {c: mb[c]["rmse"] for c in chans}, n_eff)
    return (float(math.exp(np.mean(logs))) if logs else 1.0), verdict


def with_identified_controller(cfg: AxisConfig, checks: list[dict]) -> tuple[AxisConfig, dict]:
    """The calibrated config gets the identified controller when every checked trace used it and their gains
    agree within 10 % (one controller ran them all, and it is not the config's): the virtual axis then runs
    the real axis' controller. Traces with different sidecar controllers, or a mix, leave the config's.
    Returns the config and the ``control.*`` values set (empty: none)."""
    if not checks or any(c["used"] != "identified" for c in checks):
        return cfg, {}
    ov = [c["overrides"] for c in checks]
    keys = sorted(set(ov[0]))
    if any(sorted(o) != keys for o in ov):
        return cfg, {}
    if _disagreeing_gain(ov, 1.1):  # P and PI speed loops mixed, or gains more than 10 % apart
        return cfg, {}
    merged = {k: float(np.median([float(o[k]) for o in ov])) for k in keys}
    return cfg.replace(control=merged), merged


def _align_motor_angle(td: TraceData, tr: Trace, pred: dict[str, np.ndarray], lead_m: float) -> None:
    """An encoder's zero is arbitrary: shift measured motor_pos so that it stands to a measured table-side position
    (pos_fb, else pos_meas) as the model's does, at the first samples; without one, to the model's motor_pos there.
    (The model starts at rest on the command: an axis already moving at the first sample would otherwise have its
    following error taken for the encoder's zero.)"""
    if "motor_pos" in td.measured and "motor_pos" in pred:
        mp, mp_model = td.measured["motor_pos"][:10], pred["motor_pos"][:10]
        side = next((c for c in ("pos_fb", "pos_meas") if c in td.measured and c in pred), None)
        if side is not None and lead_m > 0:
            k = 2 * math.pi / lead_m
            off = float(np.median((mp - k * td.measured[side][:10]) - (mp_model - k * pred[side][:10])))
        else:
            off = float(np.median(mp - mp_model))
        if abs(off) > 1e-3:
            td.measured["motor_pos"] = td.measured["motor_pos"] - off
            tr.warnings.append(f"motor_pos offset of {off:.4g} rad removed (encoder zero)")


def _kept(why: str, proposal: str) -> str:
    """The note of a trace whose own check proposed identified gains that the run did not take: the verdict first
    (a reader who stops early must not take the proposal for the outcome), then what the trace's check saw."""
    return f"config's controller kept: {why}" + (f"; this trace's own check had proposed otherwise: {proposal}"
                                                  if proposal else "")


def _hints(cfg: AxisConfig, traces: list[TraceData]) -> Callable:
    def hint_fn(cur: AxisConfig, res_list: list[dict]) -> dict:
        orders: list[int] = []
        for td, r in zip(traces, res_list, strict=False):
            eff = r.get("torque_meas", r.get("current_q"))
            mp = td.measured.get("motor_pos")
            if eff is not None and mp is not None:
                orders = fx.angle_orders_hint(mp, eff)
                if orders:
                    break
        return {"angle_orders": orders}

    return hint_fn


# ------------------------------------------------------------------------------------------- stages
@dataclass(frozen=True)
class LoadedTraces:
    """Stage ``load``: the traces read and checked, what the fits work on, and the fit / held-out split."""

    traces: list[Trace]
    tds: list[TraceData]
    fit_idx: list[int]
    hold_idx: list[int]
    notes: list[str]


@dataclass(frozen=True)
class CheckResult:
    """Stage ``check``: the controller each trace is simulated with (``report.json["controller_check"]``) and
    the speed feed-forward form (``report.json["feedforward_form"]``; None without feed-forward)."""

    controller_checks: list[dict]
    feedforward_form: dict | None
    notes: list[str]


@dataclass(frozen=True)
class Baseline:
    """Stage ``baseline``: the nominal model's prediction of every trace (as the trace records it), its residual,
    and how the trace records the model's channels (``report.json["alignment"]``)."""

    preds: list[dict[str, np.ndarray]]
    residuals: list[dict[str, np.ndarray]]
    alignment: list[dict]
    notes: list[str]


@dataclass(frozen=True)
class Verification:
    """The full model step by step after each accepted effect (``report.json["cumulative"]``)."""

    cumulative: list[dict]
    final_residuals: list[dict[str, np.ndarray]]
    final_preds: list[dict[str, np.ndarray]]


@dataclass(frozen=True)
class DiagnosisResult:
    """What :func:`run_diagnosis` returns: the report (``report.json``'s content), the calibrated config
    (``calibrated.toml``), the nominal config it started from, and the plots' arrays; plus each stage's result."""

    report: dict
    calibrated: AxisConfig
    nominal: AxisConfig
    plots: Plots
    check: CheckResult
    baseline: Baseline
    localisation: Localisation
    selection: Selection
    verification: Verification


def load(cfg: AxisConfig, fit_paths: list[str], holdout_paths: list[str],
         effect_names: list[str] | None = None) -> LoadedTraces:
    """Read and check every trace and its sidecar; decide the fit / held-out split."""
    traces, fit_idx, hold_idx, notes = load_traces(cfg, fit_paths, holdout_paths)
    if effect_names:
        unknown = [n for n in effect_names if n not in fx.EFFECTS]
        if unknown:
            raise InputError("--effects", f"unknown effect(s) {', '.join(unknown)}; known: {', '.join(fx.EFFECTS)}")
    tds = [TraceData.from_trace(tr, trace_overrides(tr)) for tr in traces]
    return LoadedTraces(traces, tds, fit_idx, hold_idx, notes)


def check(cfg: AxisConfig, loaded: LoadedTraces, simulate: SimulateFn) -> CheckResult:
    """The controller each trace ran (replayed, judged closed-loop) and the speed feed-forward form; a different
    one is set on the traces' overrides for every later simulation."""
    controller_checks = check_controllers(cfg, loaded.traces, loaded.tds, simulate, loaded.fit_idx, loaded.hold_idx)
    ff_form = check_feedforward_form(cfg, loaded.tds, simulate, loaded.fit_idx, loaded.hold_idx)
    notes = [ff_form["note"]] if ff_form and ff_form["used"] != ff_form["config_form"] else []
    return CheckResult(controller_checks, ff_form, notes)


def baseline(cfg: AxisConfig, loaded: LoadedTraces, simulate: SimulateFn) -> Baseline:
    """The nominal model on every trace; channels it does not produce dropped; how the trace records its
    channels (sample alignment, speed estimator, start transient); the baseline's plausibility."""
    tds, traces = loaded.tds, loaded.traces
    preds = [simulate_trace(cfg, td, simulate) for td in tds]
    for td, tr, p in zip(tds, traces, preds, strict=True):
        _align_motor_angle(td, tr, p, cfg.mechanics.lead_m)
        missing = [c for c in td.measured if c not in p]
        if missing:
            tr.warnings.append(f"channels not produced by the model of this axis, ignored: {', '.join(missing)}")
            for c in missing:
                td.measured.pop(c)
        if not td.measured:
            raise InputError(tr.path, "none of its channels can be compared with the model of this axis")
    alignment = find_alignment(tds, preds, cfg.mechanics.lead_m)
    for td, p in zip(tds, preds, strict=True):
        st = find_start_transient(td, p)
        if st:
            alignment.append(st)
    notes = [f["note"] if f["kind"] != "start_transient" else f"{f['trace']}: {f['note']}" for f in alignment]
    preds = [apply_post(td, p, cfg.mechanics.lead_m) if td.post else p for td, p in zip(tds, preds, strict=True)]
    res = [residuals(td, p) for td, p in zip(tds, preds, strict=True)]
    # the nominal model must follow the measured motion at all before any effect is fitted to the difference
    check_baseline(cfg, tds, preds)
    return Baseline(preds, res, alignment, notes)


def localise_residual(loaded: LoadedTraces, base: Baseline) -> Localisation:
    """Where the nominal residual lies: phase, direction, speed, position, time, frequency."""
    return localise([(td.name, td.t, td.pos_cmd, r) for td, r in zip(loaded.tds, base.residuals, strict=True)])


def select(cfg: AxisConfig, loaded: LoadedTraces, simulate: SimulateFn, *, jobs: int, scheduler: str | None,
           settings: FitSettings | None, effect_names: list[str] | None, progress: ProgressFn | None) -> Selection:
    """The selection rounds (:mod:`virtualaxis.diagnosis.selection`) on a process pool or Dask cluster."""
    runner = Runner(jobs=jobs, scheduler=scheduler)
    try:
        return select_effects(cfg, loaded.tds, loaded.fit_idx, loaded.hold_idx, simulate, runner, settings,
                              effect_names, progress, hint_fn=_hints(cfg, loaded.tds))
    except BaseException:  # an interrupt or error: running fits are killed, not waited for
        runner.abort()
        raise
    finally:
        runner.close()


def verify(loaded: LoadedTraces, base: Baseline, sel: Selection, simulate: SimulateFn) -> Verification:
    """Cumulative metrics with the full model, step by step."""
    fit_idx, hold_idx, tds = loaded.fit_idx, loaded.hold_idx, loaded.tds
    cumulative = []
    prev_fit = pooled_metrics([base.residuals[i] for i in fit_idx])
    prev_hold = pooled_metrics([base.residuals[i] for i in hold_idx]) if hold_idx else {}
    final_res, final_pred = base.residuals, base.preds
    for step in sel.accepted:
        preds = [simulate_trace(step.cfg, td, simulate) for td in tds]
        res = [residuals(td, p) for td, p in zip(tds, preds, strict=True)]
        fm = pooled_metrics([res[i] for i in fit_idx])
        hm = pooled_metrics([res[i] for i in hold_idx]) if hold_idx else {}
        cumulative.append({"after": step.effect, "fit_before": prev_fit, "fit_after": fm,
                           "heldout_before": prev_hold, "heldout_after": hm})
        prev_fit, prev_hold = fm, hm
        final_res, final_pred = res, preds
    return Verification(cumulative, final_res, final_pred)


def hybrid_models(loaded: LoadedTraces, ver: Verification) -> dict | None:
    """Data-driven residual models on top of the calibrated physics."""
    chans = sorted({c for r in ver.final_residuals for c in r})
    items = [(td.t, td.pos_cmd, p, r) for td, p, r in zip(loaded.tds, ver.final_preds, ver.final_residuals,
                                                           strict=True)]
    return fit_hybrid([items[i] for i in loaded.fit_idx], [items[i] for i in loaded.hold_idx], chans)


def calibrate(sel: Selection, chk: CheckResult) -> tuple[AxisConfig, dict]:
    """The calibrated config: the accepted effects, the identified controller when one ran every trace, the
    speed feed-forward form; and the controller keys it sets (``report.json["calibrated_controller"]``)."""
    calibrated, controller = with_identified_controller(sel.final_cfg, chk.controller_checks)
    ff = chk.feedforward_form
    if ff and ff["used"] != ff["config_form"]:
        calibrated = calibrated.replace(control={"velocity_ff_form": ff["used"]})
        controller = {**controller, "velocity_ff_form": ff["used"]}
    return calibrated, controller


def run_diagnosis(
    cfg: AxisConfig,
    fit_paths: list[str],
    holdout_paths: list[str] | None = None,
    *,
    simulate: SimulateFn = default_simulate,
    jobs: int = 1,
    scheduler: str | None = None,
    settings: FitSettings | None = None,
    effect_names: list[str] | None = None,
    progress: ProgressFn | None = None,
    hybrid: bool = True,
) -> DiagnosisResult:
    """Run the diagnosis, stage by stage: load -> check -> baseline -> localise -> select (screen, refine, judge,
    refit, per round) -> verify -> hybrid -> report. ``progress`` receives a
    :class:`~virtualaxis.diagnosis.progress.ProgressEvent` as each stage starts and each candidate fit ends."""
    def stage(name: str) -> None:
        if progress:
            progress(ProgressEvent(name))

    timing: dict[str, float] = {}

    def timed(key: str, t0: float) -> None:
        timing[key] = time.perf_counter() - t0

    t_start = time.perf_counter()
    stage("read")
    loaded = load(cfg, fit_paths, holdout_paths or [], effect_names)
    timed("read_s", t_start)
    t0 = time.perf_counter()
    stage("controller_check")
    chk = check(cfg, loaded, simulate)
    timed("controller_check_s", t0)
    t0 = time.perf_counter()
    stage("baseline")
    base = baseline(cfg, loaded, simulate)
    timed("baseline_s", t0)
    t0 = time.perf_counter()
    stage("localise")
    loc = localise_residual(loaded, base)
    timed("localise_s", t0)
    sel = select(cfg, loaded, simulate, jobs=jobs, scheduler=scheduler, settings=settings,
                 effect_names=effect_names, progress=progress)
    timing["fitting_s"] = sel.seconds_fitting
    t0 = time.perf_counter()
    stage("verify")
    ver = verify(loaded, base, sel, simulate)
    timed("verify_s", t0)
    t0 = time.perf_counter()
    hyb = None
    if hybrid:
        stage("hybrid")
        hyb = hybrid_models(loaded, ver)
    timed("hybrid_s", t0)
    timing["total_s"] = time.perf_counter() - t_start
    calibrated, controller = calibrate(sel, chk)
    report = build_report(cfg=cfg, loaded=loaded, check=chk, base=base, localisation=loc, selection=sel,
                          verification=ver, hybrid=hyb, timing=timing)
    if controller:
        report["calibrated_controller"] = controller
    plots = Plots(loaded.tds, base.residuals, ver.final_residuals, loc, loaded.fit_idx, loaded.hold_idx)
    return DiagnosisResult(report, calibrated, cfg, plots, chk, base, loc, sel, ver)


def _param_table(effect: str, cfg: AxisConfig, values: dict, stderr: dict) -> dict:
    params = {p.name: p for p in fx.EFFECTS[effect].params(cfg)}
    out = {}
    stderr = fx.derived_stderr(effect, values, stderr)
    for name, v in fx.derived_values(effect, values).items():
        p = params.get(name)
        se = float(stderr.get(name, float("nan")))
        out[name] = {
            "value": float(v),
            "stderr": se,
            # False: the fit traces' response to it is at the level of the model's own chaos (stderr null)
            "determined": se != math.inf,
            "unit": p.unit if p else "",
            "nominal": float(p.nominal) if p else None,
            "bounds": [p.lower, p.upper] if p else None,
        }
    return out


def _n_eff(sel, res_list: list[dict]) -> dict[str, float]:
    """Decorrelated sample count per channel of the residuals a verdict is made on."""
    frac = sel.weights.n_eff_fraction if sel.weights else {}
    return {ch: n * frac.get(ch, 1.0) for ch, n in sample_counts(res_list).items()}


def _rmse(m: dict) -> dict:
    return {ch: v["rmse"] for ch, v in m.items()}


def build_report(*, cfg: AxisConfig, loaded: LoadedTraces, check: CheckResult, base: Baseline,
                 localisation: Localisation, selection: Selection, verification: Verification, hybrid: dict | None,
                 timing: dict[str, float]) -> dict:
    """``report.json``'s content from the stages' results."""
    traces, tds, fit_idx, hold_idx = loaded.traces, loaded.tds, loaded.fit_idx, loaded.hold_idx
    notes = loaded.notes + check.notes + base.notes
    base_res, loc, sel, cumulative, hyb = base.residuals, localisation, selection, verification.cumulative, hybrid
    base_fit = pooled_metrics([base_res[i] for i in fit_idx])
    base_hold = pooled_metrics([base_res[i] for i in hold_idx]) if hold_idx else {}
    baseline = pooled_metrics(base_res)
    for ch in baseline:
        baseline[ch]["unit"] = CHANNEL_UNITS.get(ch, "")
    accepted_names = [s.effect for s in sel.accepted]
    # one entry per effect: from the round where it was accepted, else its first-round (stand-alone) fit
    entries: dict[str, dict] = {}
    for rnd, scored in enumerate(sel.rounds):
        for d in scored:
            r, s = d.result, d.score
            name = r.effect
            accepted_here = rnd < len(sel.accepted) and sel.accepted[rnd].effect == name
            if name in entries and not accepted_here:
                continue
            # the state before this round
            if rnd == 0:
                fb, hb = base_fit, base_hold
            else:
                fb, hb = cumulative[rnd - 1]["fit_after"], cumulative[rnd - 1]["heldout_after"]
            model_cfg = cfg if rnd == 0 else sel.accepted[rnd - 1].cfg
            entries[name] = {
                "name": name,
                "description": fx.EFFECTS[name].description,
                "signature": fx.EFFECTS[name].signature,
                "params": _param_table(name, model_cfg, r.values, r.stderr) if r.values else {},
                "result_values": dict(r.values),
                "params_at_bound": r.at_bound,
                "accepted": accepted_here,
                "round": rnd + 1,
                "fit": {"rmse_before": _rmse(fb), "rmse_after": _rmse(r.fit_metrics), "metrics_after": r.fit_metrics,
                        "gain": s.fit_gain},
                "heldout": {"rmse_before": _rmse(hb), "rmse_after": _rmse(r.holdout_metrics),
                            "metrics_after": r.holdout_metrics, "gain": s.gain,
                            "gain_per_channel": s.gain_per_channel},
                "judged_on": s.judged_on.value,
                "ic_delta": s.ic_delta,
                "relative_change": s.relative_change,
                "signature_overlap": r.signature_overlap,
                "pays_its_way": d.pays,
                "implausible": list(s.implausible),  # why its values are no answer (empty: they are)
                "stage": r.stage,
                "screen_gain": d.screen_gain,
                "n_simulations": r.n_sims,
                "seconds": r.seconds,
                "error": r.error,
            }
    joint = sel.joint
    # the accepted effects' parameters are the final model's (after joint refits: not the round's own fit)
    for step in sel.accepted:
        e = entries[step.effect]
        if step.values != e["result_values"]:
            e["params_sequential"] = e["params"]
            e["params"] = _param_table(step.effect, cfg, step.values, step.stderr)
            e["refit"] = "joint"
    # an accepted effect's before / after figures are the verified model's as it was added (in the order accepted,
    # with the final values): the round's own fit started from the sequential values of the effects before it,
    # which a joint refit changed, and read against the final model it could say "worse" where the model is better
    for step, c in zip(sel.accepted, cumulative, strict=True):
        e = entries[step.effect]
        for side, before, after in (("fit", "fit_before", "fit_after"), ("heldout", "heldout_before", "heldout_after")):
            if c.get(after):
                e[f"{side}_round"] = dict(e[side])
                e[side] = {**e[side], "rmse_before": _rmse(c[before]), "rmse_after": _rmse(c[after]),
                           "metrics_after": c[after]}
    for e in entries.values():
        e.pop("result_values", None)
    ranked = [entries[n] for n in accepted_names] + sorted(
        (e for n, e in entries.items() if n not in accepted_names), key=lambda e: e["ic_delta"])
    for k, e in enumerate(ranked):
        e["rank"] = k + 1
    where = [e for e in loc.entries]
    summary = {ch: [{"dimension": e["dimension"], "bin": e["bin"], "share": e["share"],
                     "concentration": e["share"] / e["time_fraction"]} for e in loc.concentrations(ch)[:5]]
               for ch in baseline}
    spectra = {ch: {k: v for k, v in sp.items() if k not in ("f_hz", "psd")} for ch, sp in loc.spectra.items()}
    conclusion = " + ".join(accepted_names) if accepted_names else NO_EFFECT
    mismatch = sel.mismatch
    if mismatch:
        where_txt = ", ".join(f"{e['dimension']} {e['bin']} ({100 * e['share']:.0f} % of it)"
                              for e in mismatch["where"][:3])
        # judged on held-out traces only when there are some: an effect explaining part of the one fit trace's
        # residual (its own noise, coloured by the loops, included) with parameters the trace cannot determine
        # is a hint, not a finding
        mismatch["judged_on"] = "holdout" if hold_idx else "fit"
        decided = bool(hold_idx)
        mismatch["description"] = (
            f"{'unexplained' if decided else 'possible'} model-form mismatch in {mismatch['target_channel']}"
            + (f", concentrated in {where_txt}" if where_txt else "")
            + f": the closest library effect, {mismatch['closest_effect']}, would explain "
            f"{100 * mismatch['heldout_gain']:.0f} % of the {'held-out' if decided else 'fit'} residual, but it is no "
            f"answer ({'; '.join(mismatch['why_not'])})"
            + ("" if decided else "; judged on the fit trace only, so not concluded: held-out traces decide"))
        notes = notes + [mismatch["description"]]
        if decided:
            conclusion = (conclusion + " + " if accepted_names else "") + "unexplained model-form mismatch"
    gap = _unexplained_gap(hyb) if conclusion == NO_EFFECT else None
    if gap:
        notes = notes + [gap["description"]]
        conclusion = UNEXPLAINED_GAP
    for r in sel.removed:
        notes = notes + [f"{r['effect']} removed again after round {r['round']} (backward step): {r['why']}"]
    for n in accepted_names:
        loose = [k for k, v in entries[n]["params"].items() if not v["determined"]]
        if loose:
            notes = notes + [
                f"{n}: {', '.join(loose)} not determined by the fit traces (their response to "
                f"{'it' if len(loose) == 1 else 'them'} is at the level of the model's own chaos); the "
                f"{'value is' if len(loose) == 1 else 'values are'} the best of a broad basin and the effect is "
                "accepted on its held-out gain. Record a fit trace that excites it (a mode: a rapid move with short "
                "jerk phases, or a sine sweep through its band; a Stribeck velocity: slow reversals) to pin it "
                "down"]
    # the binned force vs speed per direction with the calibrated friction law over it, judged against the
    # calibrated model's own prediction run through the same estimate
    fvs = friction_law.force_vs_speed(sel.final_cfg, tds, accepted_names, verification.final_preds)
    if fvs and fvs.get("note"):
        notes = notes + [fvs["note"]]
    final_fit = cumulative[-1]["fit_after"] if cumulative else base_fit
    final_hold = cumulative[-1]["heldout_after"] if cumulative else base_hold
    n_eff = _n_eff(sel, [base_res[i] for i in (hold_idx or fit_idx)])
    final_verdict = channel_verdict(_rmse(base_hold or base_fit), _rmse(final_hold or final_fit), n_eff)
    if accepted_names and final_verdict["worse_channels"]:
        # the accepted effects leave a channel worse than the nominal model: they explain part of the gap, and a
        # value may stand in for a mechanism the library does not hold (where the nominal gap concentrated)
        worse = final_verdict["worse_channels"]
        where_txt = "; ".join(f"{ch} in {v[0]['dimension']} {v[0]['bin']}" for ch, v in summary.items() if v)
        notes = notes + [
            f"the calibrated model is worse beyond its noise than the nominal one in {', '.join(worse)} on the "
            f"{'held-out' if hold_idx else 'fit'} traces: {' + '.join(accepted_names)} explain"
            f"{'s' if len(accepted_names) == 1 else ''} part of the gap only, and "
            f"{'its value' if len(accepted_names) == 1 else 'their values'} may stand in for a mechanism outside "
            "the library" + (f" (the nominal gap concentrates: {where_txt})" if where_txt else "")]
    for e in entries.values():  # per-channel before/after of every candidate, held out (or on the fit traces)
        side = e["heldout"] if hold_idx else e["fit"]
        e["verdict"] = channel_verdict(side["rmse_before"], side["rmse_after"], n_eff)
    stages = [
        {"stage": "load", "seconds": timing.get("read_s"), "fit": [traces[i].name for i in fit_idx],
         "holdout": [traces[i].name for i in hold_idx]},
        {"stage": "check", "seconds": timing.get("controller_check_s"),
         "controller": [c["used"] for c in check.controller_checks],
         "feedforward_form": check.feedforward_form["used"] if check.feedforward_form else None},
        {"stage": "baseline", "seconds": timing.get("baseline_s"),
         "alignment": [f["kind"] for f in base.alignment]},
        {"stage": "localise", "seconds": timing.get("localise_s"),
         "where": {ch: v[0] for ch, v in summary.items() if v}},
        *sel.trail,
        {"stage": "verify", "seconds": timing.get("verify_s"), "after": [c["after"] for c in cumulative]},
        {"stage": "report", "conclusion": conclusion},
    ]
    return {
        "format": "virtualaxis-gap-diagnosis/1",
        "config": cfg.path,
        "axis": cfg.axis.name,
        "axis_model": {"mechanics": cfg.mechanics.model, "actuator": cfg.actuator.kind},
        "traces": [
            {"name": tr.name, "path": tr.path, "role": "fit" if i in fit_idx else "holdout", "samples": int(tr.t.size),
             "sample_period_s": tr.dt_s, "channels": sorted(tds[i].measured), "warnings": tr.warnings,
             "metadata": {k: v for k, v in tr.metadata.items() if isinstance(v, (str, int, float, bool))}}
            for i, tr in enumerate(traces)
        ],
        "warnings": notes + [f"{tr.name}: {w}" for tr in traces for w in tr.warnings],
        "baseline": baseline,
        "baseline_fit": base_fit,
        "baseline_heldout": base_hold,
        "where": where,
        "where_summary": summary,
        "spectra": spectra,
        "conclusion": conclusion,
        "accepted": accepted_names,
        "effects": ranked,
        "not_applicable": sel.skipped,
        "joint_refit": joint,
        # sigma_c of every cost: max(noise floor, 0.1 x baseline rms, quantum / sqrt 12, model chaos)
        "channel_weights": {ch: {"sigma": sg, "quantum": sel.weights.quantum.get(ch, 0.0),
                                 "chaos": sel.weights.chaos.get(ch, 0.0),
                                 "n_eff_fraction": sel.weights.n_eff_fraction.get(ch, 1.0)}
                            for ch, sg in sel.weights.sigma.items()} if sel.weights else {},
        "cumulative": cumulative,
        "model_form_mismatch": mismatch,
        "unexplained_gap": gap,
        "removed_by_backward_step": sel.removed,
        "force_vs_speed": fvs,
        "final": {"fit": final_fit, "heldout": final_hold,
                  "verdict": final_verdict,
                  "heldout_rmse_ratio": {ch: base_hold[ch]["rmse"] / max(final_hold[ch]["rmse"], 1e-300)
                                         for ch in final_hold if ch in base_hold}},
        "hybrid": hyb,
        "timing": {**timing, "simulations": sel.n_sims},
        "stages": stages,
        "controller_check": check.controller_checks,
        "feedforward_form": check.feedforward_form,
        "alignment": base.alignment,
        "contour": contour_report(tds, {"nominal": base.preds, "calibrated": verification.final_preds}),
    }


def write_outputs(result: DiagnosisResult, out_dir: str | Path) -> dict[str, Path]:
    """``report.json``, ``report.html``, ``calibrated.toml`` (and ``force_vs_speed.png``) into ``out_dir``."""
    report = result.report
    paths = write_report(report, Path(out_dir), calibrated=result.calibrated, nominal=result.nominal,
                         plots=result.plots)
    if report.get("force_vs_speed"):  # the plot of report.json["force_vs_speed"]
        png = Path(out_dir) / "force_vs_speed.png"
        png.write_bytes(friction_law.plot_png(report["force_vs_speed"]))
        paths["force_vs_speed"] = png
    return paths


def _unexplained_gap(hyb: dict | None) -> dict | None:
    """No library effect accepted, yet a learned residual model judged on held-out traces removes most of a
    position channel's residual (at most :data:`SYSTEMATIC_GAP_RATIO` of its RMSE left, better beyond its noise,
    no channel worse beyond it): the model misses something systematic that the library does not describe.
    None otherwise (one trace: the learned model is judged on the trace it was fitted to, which proves nothing)."""
    if not hyb or not hyb.get("model") or hyb.get("judged_on") != "holdout" or not hyb.get("improves"):
        return None
    v = hyb["verdict"]
    chans = [c for c in ("pos_meas", "pos_fb", "motor_pos") if c in v["better_channels"]
             and v["channels"][c]["ratio"] <= SYSTEMATIC_GAP_RATIO]
    if not chans:
        return None
    from virtualaxis.diagnosis.report import verdict_text

    c = chans[0]
    ch = v["channels"][c]
    return {"channel": c, "rmse_before": ch["before"], "rmse_after_learned": ch["after"], "model": hyb["model"],
            "description": f"unexplained systematic gap in {c}: no library effect explains it, but a learned residual "
                           f"model ({hyb['model']}) predicts it on the held-out traces (RMSE "
                           f"{verdict_text({'channels': {c: ch}})}, {100 * (1 - ch['ratio']):.0f} % less): the model "
                           "misses a mechanism, or a recording delay or filter the trace format does not describe"}
