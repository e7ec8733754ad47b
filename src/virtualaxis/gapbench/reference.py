"""Diagnose the independent reference axis' cases and score the diagnosis against their truth.

A case (``virtualaxis.refaxis.make_case``) is a nominal config in our schema, fit and held-out traces, and the
truth: which effects were withheld and their main parameter values. Scoring (the bench's acceptance figures):

- right effect first: the first accepted effect is one of the withheld ones;
- clean: nothing accepted;
- nothing outside the truth: every accepted effect is a withheld one (clean: none);
- main parameter within 15 %: for each withheld effect that was accepted, its main parameter;
- held-out RMSE shrink on the channel the effect shows in (the truth's channel when it names one, else the channel
  the calibrated model shrank most), with the truth model's ceiling beside it when the case provides one.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from virtualaxis.diagnosis.effects import EFFECTS, derived_values

#: a parameter counts as recovered within this relative error
PARAM_TOLERANCE = 0.15
#: held-out RMSE shrink the issue asks for on the effect's channel
SHRINK_TARGET = 0.60


def _get(obj: Any, key: str, default=None):
    if isinstance(obj, dict):
        return obj.get(key, default)
    return getattr(obj, key, default)


def truth_effects(truth: Any) -> list[str]:
    """Withheld effects of a case's truth (library names); [] for a clean case."""
    eff = _get(truth, "effects", None)
    if eff is None:
        eff = list((_get(truth, "params", {}) or {}).keys())
    return [str(e) for e in eff]


#: withheld "effects" of the reference that are not plant effects but how the trace records the axis; the
#: diagnosis answers them with an alignment finding (``report.json["alignment"]``), not an accepted effect. (A
#: speed estimator inside the loop is a library effect, ``speed_estimator``, and scored as one.)
RECORDING_EFFECTS = {"moving_start": "start_transient", "channel_shift": "channel_shift"}


def _fitted_name(effect: str, truth_key: str) -> str | None:
    """Our fitted parameter name for a truth key (``backlash.gap_m`` -> ``gap_m``; ``effect/param`` and bare
    names through the library's ``truth_keys`` or the last name component)."""
    eff = EFFECTS.get(effect)
    if eff is None:
        return None
    tail = truth_key.replace("/", ".").rsplit(".", 1)[-1]
    for tk, name in eff.truth_keys:
        if tk == truth_key or tk.rsplit(".", 1)[-1] == tail or name == tail or name.endswith(tail):
            return name
    names = [p.name for p in eff.params(_ANY_CFG[0])] if _ANY_CFG else []
    return tail if tail in names else None


_ANY_CFG: list = []


def truth_params(truth: Any) -> dict[str, dict[str, float]]:
    """``{effect: {fitted param: true value}}`` of the withheld effects' main parameters (the truth's
    ``main_param``; else every numeric parameter the library can name)."""
    params = _get(truth, "params", None) or {}
    main = _get(truth, "main_param", None) or {}
    out: dict[str, dict[str, float]] = {}
    for eff in truth_effects(truth):
        keys = [main[eff]] if eff in main else list(params)
        for key in keys:
            v = params.get(key)
            name = _fitted_name(eff, key)
            if isinstance(v, (int, float)) and name:
                out.setdefault(eff, {})[name] = float(v)
    return out


def truth_channel(truth: Any) -> str | None:
    ch = _get(truth, "channel", None) or _get(truth, "shows_in", None)
    return str(ch) if ch else None


def evaluate_reference_case(name: str, truth: Any, report: dict, truth_metrics: dict | None = None) -> dict:
    """Score one diagnosis report against the case's truth (see the module docstring)."""
    withheld = truth_effects(truth)
    accepted = list(report["accepted"])
    ranked = [e["name"] for e in report["effects"]]
    found_kinds = {f["kind"] for f in report.get("alignment", [])}
    recording = [e for e in withheld if e in RECORDING_EFFECTS]
    # an answer is the accepted plant effects followed by the recording findings
    answer = accepted + [e for e, kind in RECORDING_EFFECTS.items() if kind in found_kinds]
    if recording and not accepted:
        top1 = all(RECORDING_EFFECTS[e] in found_kinds for e in recording)
    else:
        top1 = (bool(accepted) and accepted[0] in withheld) if withheld else not accepted
    outside = [a for a in accepted if a not in withheld]
    rec: dict[str, dict] = {}
    tparams = truth_params(truth)
    for e in report["effects"]:
        if not e["accepted"] or e["name"] not in tparams:
            continue
        vals = derived_values(e["name"], {k: v["value"] for k, v in e["params"].items()})
        for pname, true_v in tparams[e["name"]].items():
            if pname in vals and true_v:
                p = e["params"].get(pname, {})
                se = p.get("stderr") if p.get("determined", True) else None
                rec[f"{e['name']}.{pname}"] = {"true": true_v, "fitted": vals[pname],
                                               "rel_error": abs(vals[pname] - true_v) / abs(true_v),
                                               "stderr": se}
    missed_params = [f"{e}.{p}" for e, d in tparams.items() for p in d if f"{e}.{p}" not in rec]
    hold = report["baseline_heldout"] or report["baseline_fit"]
    fin = report["final"]["heldout"] or report["final"]["fit"]
    shrink = {ch: 1.0 - fin[ch]["rmse"] / hold[ch]["rmse"] for ch in fin if ch in hold and hold[ch]["rmse"] > 0}
    tm = truth_metrics or {}
    ceiling = {ch: 1.0 - tm[ch]["rmse"] / hold[ch]["rmse"] for ch in shrink if ch in tm and hold[ch]["rmse"] > 0}
    ch = truth_channel(truth)
    if ch not in shrink:
        # the truth does not name the channel the effect shows in: the channel where the calibrated model shrank
        # the held-out RMSE most (as the own-simulator bench's "best channel")
        ch = max(shrink, key=shrink.get) if shrink else None
    return {
        "case": name, "truth": withheld, "accepted": accepted, "answer": answer, "ranked": ranked[:4],
        "alignment": [f.get("note", "") for f in report.get("alignment", [])],
        "conclusion": report["conclusion"], "top1": top1, "outside_truth": outside, "none_outside": not outside,
        "false_positive": (not withheld) and bool(accepted), "param_recovery": rec, "params_not_found": missed_params,
        "effect_channel": ch, "heldout_rmse_shrink": shrink, "shrink_on_effect_channel": shrink.get(ch, math.nan),
        "truth_model_ceiling": ceiling.get(ch, math.nan) if ch else math.nan,
        "final_verdict_improves": report["final"].get("verdict", {}).get("improves"),
        "model_form_mismatch": (report.get("model_form_mismatch") or {}).get("description"),
        "controller": [c.get("used") for c in report.get("controller_check", [])],
        "seconds": report["timing"]["total_s"],
    }


def summarise_reference(results: list[dict]) -> dict:
    """The issue's acceptance figures over the scored cases."""
    def num(x) -> float:  # NaN is written to JSON as null
        return math.nan if x is None else float(x)

    results = [{**r, "shrink_on_effect_channel": num(r["shrink_on_effect_channel"]),
                "truth_model_ceiling": num(r["truth_model_ceiling"])} for r in results]
    eff = [r for r in results if r["truth"]]
    clean = [r for r in results if not r["truth"]]
    # a withheld parameter that was not found counts as not recovered
    recs = [v["rel_error"] for r in eff for v in r["param_recovery"].values()] + \
        [math.inf for r in eff for _ in r["params_not_found"]]
    # recording conventions (moving start, channel shift, estimator) have no plant effect whose gap could shrink
    shr = [r for r in eff if math.isfinite(r["shrink_on_effect_channel"])
           and any(e not in RECORDING_EFFECTS for e in r["truth"])]

    def mean(x):
        return float(np.mean(x)) if len(x) else math.nan

    return {
        "n_effect_cases": len(eff), "n_clean_cases": len(clean),
        "right_effect_first": mean([r["top1"] for r in eff]),
        "clean_nothing_accepted": mean([not r["false_positive"] for r in clean]),
        "none_outside_truth": mean([r["none_outside"] for r in results]),
        "param_within_15pct": mean([x <= PARAM_TOLERANCE for x in recs]),
        "param_rel_error_median": float(np.median(recs)) if recs else math.nan,
        # reported uncertainty: of the found main parameters with a standard error, the share whose true value
        # lies within two of them (and how many were reported as not determined by the fit traces)
        "param_within_2_stderr": mean([abs(v["fitted"] - v["true"]) <= 2 * v["stderr"] for r in eff
                                       for v in r["param_recovery"].values()
                                       if v.get("stderr") is not None and math.isfinite(v["stderr"])]),
        "param_n_with_stderr": sum(1 for r in eff for v in r["param_recovery"].values()
                                   if v.get("stderr") is not None and math.isfinite(v["stderr"])),
        "param_n_undetermined": sum(1 for r in eff for v in r["param_recovery"].values() if v.get("stderr") is None),
        "shrink_ge_60pct": mean([r["shrink_on_effect_channel"] >= SHRINK_TARGET for r in shr]),
        "shrink_ge_60pct_or_ceiling": mean([
            r["shrink_on_effect_channel"] >= min(SHRINK_TARGET, 0.9 * r["truth_model_ceiling"])
            if math.isfinite(r["truth_model_ceiling"]) else r["shrink_on_effect_channel"] >= SHRINK_TARGET
            for r in shr]),
    }


def run_reference_bench(out_dir: Path, seed: int = 0, case_names: list[str] | None = None, quick: bool = False,
                        jobs: int = 1, progress=None, door: str = "cli") -> dict:
    """Make the reference cases, diagnose each with the nominal config the case provides, score; writes
    ``reference.json`` and each case's report under ``out_dir/<case>/diagnosis``.

    ``door="cli"`` (the default) runs ``virtualaxis diagnose`` on the case's files in a subprocess, as a user
    does (its command line and output in ``<case>/diagnosis.log``); a case where it exits non-zero is listed in
    ``reference.json["failed"]`` with the CLI's error line, is not scored, and the bench goes on. ``"library"``
    calls the pipeline in-process."""
    from virtualaxis.config import load_axis_config
    from virtualaxis.config.errors import InputError
    from virtualaxis.diagnosis.bench import DOORS, DiagnoseFailed, diagnose_through_cli
    from virtualaxis.diagnosis.fit import FitSettings
    from virtualaxis.diagnosis.pipeline import run_diagnosis, write_outputs
    from virtualaxis.diagnosis.report import report_json
    from virtualaxis.refaxis import case_names as ref_case_names
    from virtualaxis.refaxis import make_case

    known = list(ref_case_names())
    names = case_names or known
    unknown = [n for n in names if n not in known]
    if unknown:
        raise InputError("--cases", f"unknown reference case(s) {', '.join(unknown)}; known: {', '.join(known)}")
    if door not in DOORS:
        raise ValueError(f"door must be one of {DOORS}, got {door!r}")
    results: list[dict] = []
    failed: list[dict] = []
    t0 = time.perf_counter()
    out: dict = {}
    for k, name in enumerate(names):
        cdir = Path(out_dir) / name.replace("/", "__")
        # the case's seed from its place in the full list: a case draws the same noise whether it runs alone
        # (--cases, a bench run in chunks) or with all the others
        cf = make_case(name, cdir, seed=seed + known.index(name), quick=quick)
        cfg = load_axis_config(cf.config_path)
        _ANY_CFG[:] = [cfg]
        fit, hold = [str(p) for p in cf.fit], [str(p) for p in cf.holdout]
        (cdir / "score.json").unlink(missing_ok=True)
        if door == "cli":
            try:
                rep = diagnose_through_cli(cf.config_path, fit, hold, cdir / "diagnosis", jobs=jobs,
                                           hybrid=not quick)
            except DiagnoseFailed as exc:
                ev = {"case": name, "failed": True, "exit_code": exc.exit_code, "error": exc.message,
                      "log": str(exc.log_path)}
                failed.append(ev)
                out = _write_summary(out_dir, seed, quick, results, t0, complete=k == len(names) - 1,
                                     failed=failed)
                if progress:
                    progress(ev)
                continue
        else:
            result = run_diagnosis(cfg, fit, hold, jobs=jobs, settings=FitSettings(), hybrid=not quick)
            write_outputs(result, cdir / "diagnosis")
            rep = result.report
        ev = evaluate_reference_case(name, cf.truth, rep, _truth_metrics(cf, rep))
        ev["door"] = rep.get("_door", {"door": "library"})
        results.append(ev)
        (cdir / "score.json").write_text(report_json(ev), encoding="utf-8")
        out = _write_summary(out_dir, seed, quick, results, t0, complete=k == len(names) - 1, failed=failed)
        if progress:
            progress(ev)
    return out


def summarise_by_structure(results: list[dict]) -> dict[str, dict]:
    """:func:`summarise_reference` per structure of the reference (the case name's part before the "/")."""
    groups: dict[str, list[dict]] = {}
    for r in results:
        groups.setdefault(str(r["case"]).split("/", 1)[0], []).append(r)
    return {k: summarise_reference(v) for k, v in groups.items()}


def _write_summary(out_dir: Path, seed: int, quick: bool, results: list[dict], t0: float, complete: bool,
                   failed: list[dict] | None = None) -> dict:
    """``reference.json`` after every case (a long run that is stopped keeps what it scored)."""
    from virtualaxis.diagnosis.report import report_json

    summary = summarise_reference(results)
    summary["by_structure"] = summarise_by_structure(results)
    summary["seconds"] = time.perf_counter() - t0
    summary["n_failed"] = len(failed or [])
    out = {"generator": "virtualaxis.refaxis", "seed": seed, "quick": quick, "complete": complete,
           "summary": summary, "cases": results, "failed": list(failed or [])}
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / "reference.json").write_text(report_json(out), encoding="utf-8")
    return out


def _truth_metrics(cf: Any, report: dict) -> dict | None:
    """Held-out residual metrics of the reference's own noise-free prediction, when the case provides one
    (``truth["ceiling_rmse"]``: {channel: rmse}); None otherwise."""
    ceil = _get(cf.truth, "ceiling_rmse", None) or _get(cf.truth, "heldout_floor_rmse", None)
    if isinstance(ceil, dict):
        return {ch: {"rmse": float(v)} for ch, v in ceil.items()}
    return None


def rescore_reference(out_dir: Path, seed: int = 0, quick: bool = False) -> dict:
    """Summarise every case scored under ``out_dir`` (``<case>/score.json``, in the reference's case order): a
    bench run in chunks (``--cases``) into one directory gives the figures of the whole. Rewrites
    ``reference.json``."""
    from virtualaxis.refaxis import case_names as ref_case_names

    results = []
    for name in ref_case_names():
        f = Path(out_dir) / name.replace("/", "__") / "score.json"
        if f.exists():
            ev = load_json(f)
            for k in ("shrink_on_effect_channel", "truth_model_ceiling"):  # NaN was written as null
                ev[k] = math.nan if ev.get(k) is None else float(ev[k])
            results.append(ev)
    if not results:
        from virtualaxis.config.errors import InputError

        raise InputError(str(out_dir), "no scored reference case (<case>/score.json) in this directory")
    out = _write_summary(out_dir, seed, quick, results, time.perf_counter(), complete=True)
    out["summary"]["seconds"] = float(sum(r.get("seconds", 0.0) for r in results))
    return out


def load_json(path: Path) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))
