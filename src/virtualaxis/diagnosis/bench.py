"""The gap bench: withheld-effect cases with a known answer.

A case is a *truth* config (the nominal config plus one or two effects at a realistic size, or
nothing) and the *nominal* config without them. "Measured" traces are simulated from the truth with
sensor noise and quantisation on (a seed per trace); the diagnosis sees only the traces and the
nominal config. Conditions follow seed 000: sine commands F1000..F6000 mm/min (fit on F1000 and
F6000 plus a point-to-point move, hold out F2000..F5000 and a two-axis circle); ``quick`` uses a
10 mm stroke and short traces for the test suite.

Two axes: the seed 000 ball-screw axis (PMSM, cascade) and a rigid single-mass axis driven by a
force actuator (linear motor, P/PI cascade with a force output; only scale position + force).
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virtualaxis.config import AxisConfig, load_axis_config
from virtualaxis.diagnosis.effects import EFFECTS, derived_values
from virtualaxis.diagnosis.trace import write_trace
from virtualaxis.resources import project_file

EXAMPLES = project_file("configs/examples")
BALLSCREW_CONFIG = EXAMPLES / "gap-bench-ballscrew.toml"
RIGID_CONFIG = EXAMPLES / "rigid-force-axis.toml"


@dataclass
class Case:
    name: str
    axis: str  # "ballscrew" | "rigid"
    effects: tuple[str, ...]  # withheld effects (the answer); () = clean
    truth: dict  # config changes of the truth: {section: {key: value}}
    truth_params: dict = field(default_factory=dict)  # {effect: {param: value}} expected from the fit


#: the controller of the "rigid-pp-*" cases: P position loop, P velocity loop (the config has P/PI, Kv 40, Kp 8000)
PP_CASCADE = {"kv_per_s": 25.0, "velocity_kp_n_s_per_m": 5000.0, "speed_ti_s": 0.0}


def _case(name, axis, effects, truth, params):
    return Case(name, axis, tuple(effects), truth, params)


def all_cases() -> list[Case]:
    """Every case of the bench (the nominal configs are the example files)."""
    c = [
        _case("backlash", "ballscrew", ["backlash"], {"backlash": {"enabled": True, "gap_m": 20e-6}},
              {"backlash": {"gap_m": 20e-6}}),
        _case("coulomb_friction", "ballscrew", ["coulomb_friction"], {"friction": {"coulomb_n": 110.0}},
              {"coulomb_friction": {"coulomb_n": 110.0}}),
        _case("stribeck_friction", "ballscrew", ["stribeck_friction"],
              {"friction": {"stribeck_n": 60.0, "stribeck_velocity_m_s": 2e-3}},
              {"stribeck_friction": {"stribeck_n": 60.0}}),
        _case("viscous_friction", "ballscrew", ["viscous_friction"], {"friction": {"viscous_n_s_per_m": 1500.0}},
              {"viscous_friction": {"viscous_n_s_per_m": 1500.0}}),
        _case("friction_asymmetry", "ballscrew", ["friction_asymmetry"], {"friction": {"coulomb_negative_n": 100.0}},
              {"friction_asymmetry": {"coulomb_n": 40.0, "coulomb_negative_n": 100.0}}),
        _case("mass_error", "ballscrew", ["mass_error"], {"mechanics": {"table_mass_kg": 230.0}},
              {"mass_error": {"table_mass_kg": 230.0}}),
        _case("axial_compliance", "ballscrew", ["axial_compliance"], {"_stiffness_scale": 0.25},
              {"axial_compliance": {"axial_stiffness_scale": 0.25}}),
        # 20 kg of the weighed 150 kg moving mass on a 45 Hz spring (the config's table mass is the total)
        _case("resonance", "ballscrew", ["resonance"],
              {"mechanics": {"table_mass_kg": 130.0},
               "effects": {"resonance_frequency_hz": 45.0, "resonance_mass_kg": 20.0, "resonance_damping_ratio": 0.03}},
              {"resonance": {"resonance_frequency_hz": 45.0}}),
        _case("lead_error", "ballscrew", ["lead_error"],
              {"effects": {"lead_error_ppm": 60.0, "lead_error_periodic_m": 3e-6,
                           "lead_error_periodic_phase_rad": 0.5}},
              {"lead_error": {"lead_error_ppm": 60.0, "lead_error_periodic_m": 3e-6}}),
        _case("torque_ripple", "ballscrew", ["torque_ripple"],
              {"motor": {"cogging_amplitude_nm": 0.5, "cogging_periods_per_rev": 24.0, "cogging_phase_rad": 0.3}},
              {"torque_ripple": {"cogging_amplitude_nm": 0.5}}),
        _case("time_delay", "ballscrew", ["time_delay"], {"sensors": {"dead_time_s": 2e-3}},
              {"time_delay": {"dead_time_s": 2e-3}}),
        _case("thermal_drift", "ballscrew", ["thermal_drift"],
              {"effects": {"thermal_expansion_per_k": 11.5e-6, "initial_temperature_rise_k": 5.0}},
              {"thermal_drift": {"initial_temperature_rise_k": 5.0}}),
        _case("backlash+coulomb", "ballscrew", ["backlash", "coulomb_friction"],
              {"backlash": {"enabled": True, "gap_m": 20e-6}, "friction": {"coulomb_n": 110.0}},
              {"backlash": {"gap_m": 20e-6}, "coulomb_friction": {"coulomb_n": 110.0}}),
        _case("mass+viscous", "ballscrew", ["mass_error", "viscous_friction"],
              {"mechanics": {"table_mass_kg": 230.0}, "friction": {"viscous_n_s_per_m": 1500.0}},
              {"mass_error": {"table_mass_kg": 230.0}, "viscous_friction": {"viscous_n_s_per_m": 1500.0}}),
        _case("clean", "ballscrew", [], {}, {}),
        _case("clean-2", "ballscrew", [], {}, {}),
        _case("rigid-coulomb", "rigid", ["coulomb_friction"], {"friction": {"coulomb_n": 90.0}},
              {"coulomb_friction": {"coulomb_n": 90.0}}),
        _case("rigid-mass", "rigid", ["mass_error"], {"mechanics": {"table_mass_kg": 110.0}},
              {"mass_error": {"table_mass_kg": 110.0}}),
        _case("rigid-viscous", "rigid", ["viscous_friction"], {"friction": {"viscous_n_s_per_m": 900.0}},
              {"viscous_friction": {"viscous_n_s_per_m": 900.0}}),
        _case("rigid-clean", "rigid", [], {}, {}),
        # another controller than the config's (P/P cascade, other gains; the diagnosis is not told): the
        # controller check must identify it, then the plant is judged (last, so the other cases keep their seeds)
        _case("rigid-pp-clean", "rigid", [], {"control": dict(PP_CASCADE)}, {}),
        _case("rigid-pp-coulomb", "rigid", ["coulomb_friction"],
              {"control": dict(PP_CASCADE), "friction": {"coulomb_n": 90.0}},
              {"coulomb_friction": {"coulomb_n": 90.0}}),
    ]
    return c


QUICK_CASES = ("backlash", "coulomb_friction", "mass_error", "clean")


def nominal_config(axis: str) -> AxisConfig:
    return load_axis_config(BALLSCREW_CONFIG if axis == "ballscrew" else RIGID_CONFIG)


def truth_config(nominal: AxisConfig, case: Case) -> AxisConfig:
    changes = {k: dict(v) for k, v in case.truth.items() if not k.startswith("_")}
    cfg = nominal.replace(**changes) if changes else nominal
    if "_stiffness_scale" in case.truth:
        cfg = EFFECTS["axial_compliance"].apply(cfg, {"axial_stiffness_scale": case.truth["_stiffness_scale"]})
    return cfg


@dataclass
class Condition:
    name: str
    spec: str
    duration_s: float
    role: str  # "fit" | "holdout"
    axis_name: str = ""  # which axis of a multi-axis profile


def conditions(quick: bool) -> list[Condition]:
    """Seed 000's tests. ``quick``: 10 mm stroke, about 2 s per trace (for the test suite)."""
    stroke = 10.0 if quick else 100.0
    out = []
    for f in (1000, 2000, 3000, 4000, 5000, 6000):
        period = math.pi * stroke * 1e-3 / (f / 6e4)  # 2 pi A / v, A = stroke / 2
        dur = min(max(period * (1.0 if not quick else 1.0), 1.0 if quick else 3.0), 4.0 if quick else 20.0)
        role = "fit" if f in (1000, 6000) else "holdout"
        if quick and role == "holdout" and f not in (3000,):
            continue
        out.append(Condition(f"sine_F{f}", f"sine:stroke_mm={stroke:g},feed_mm_min={f}", dur, role))
    dist = 5.0 if quick else 50.0
    out.append(Condition("ptp", f"ptp:distance_mm={dist:g},feed_mm_min=3000,accel_m_s2=1,jerk_m_s3=20,dwell_s=0.2",
                         0.0, "fit"))
    if not quick:
        for ax in ("x", "y"):
            out.append(Condition(f"circle_{ax}", "circle:radius_mm=30,omega_rad_min=120", 3.2, "holdout", ax))
        # a rapid traverse (G0) as a machine makes it: 2 ms jerk phases, the only fit trace with content near a
        # structural mode (the 50 ms jerk phases of the move above and the sines excite nothing above ~20 Hz)
        out.append(Condition("ptp_rapid", "ptp:distance_mm=50,feed_mm_min=10000,accel_m_s2=2,jerk_m_s3=1000,"
                             "dwell_s=0.2", 0.0, "fit"))
    return out


def _command(cfg: AxisConfig, cond: Condition) -> tuple[np.ndarray, np.ndarray]:
    from virtualaxis.sim.profiles import parse_profile, sample_profile

    prof = parse_profile(cond.spec, cfg)
    dur = cond.duration_s or prof.natural_duration_s
    if cond.name.startswith("ptp"):  # there and back
        dur = prof.natural_duration_s
    cyc = cfg.control.position_cycle_s
    t = np.arange(int(round(dur / cyc)) + 1) * cyc
    sampled = sample_profile(prof, t, dur)
    key = cond.axis_name if cond.axis_name in sampled else next(iter(sampled))
    pos = sampled[key][0]
    if cond.name.startswith("ptp"):
        pos = np.concatenate([pos, pos[-1] - (pos - pos[0])])
        t = np.arange(pos.size) * cyc
    return t, pos


def generate_case(case: Case, out_dir: Path, seed: int, quick: bool) -> dict:
    """Write the case: nominal.toml, truth.json, fit/*.csv, holdout/*.csv."""
    from virtualaxis.diagnosis.data import settled
    from virtualaxis.sim import simulate_command

    nominal = nominal_config(case.axis)
    truth = truth_config(nominal, case)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "fit").mkdir(exist_ok=True)
    (out_dir / "holdout").mkdir(exist_ok=True)
    (out_dir / "nominal.toml").write_text(nominal.to_toml(f"gap bench case {case.name}: nominal config"),
                                          encoding="utf-8")
    keep = _channels(case.axis)
    files: dict[str, list[str]] = {"fit": [], "holdout": []}
    for k, cond in enumerate(conditions(quick)):
        t, pos = _command(nominal, cond)
        # enabled and settled before the recording starts, as the diagnosis' model is (data.settled)
        res = settled(lambda c, tt, pp, ff, sd: simulate_command(c, tt, pp, force_ext_n=ff, seed=sd), truth, t, pos,
                      None, seed * 1000 + k)
        cols = {"t": t, "pos_cmd": pos, **{c: res[c] for c in keep if c in res}}
        path = out_dir / cond.role / f"{cond.name}.csv"
        write_trace(path, cols)
        files[cond.role].append(str(path))
    meta = {"case": case.name, "axis": case.axis, "effects": list(case.effects), "truth_changes": case.truth,
            "truth_params": case.truth_params, "seed": seed, "quick": quick, "files": files}
    (out_dir / "truth.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    return meta


def _channels(axis: str) -> tuple[str, ...]:
    if axis == "rigid":  # a prismatic axis identified from scale position and the controller's force
        return ("pos_meas", "force_drive")
    return ("pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q")


def truth_model_metrics(case: Case, meta: dict, simulate=None) -> dict:
    """Held-out residual metrics of the *truth* model (what a perfect diagnosis would leave: sensor noise,
    the closed loop's response to it, quantisation). Only the bench knows it; the diagnosis never sees it."""
    from virtualaxis.diagnosis.data import TraceData, default_simulate, pooled_metrics, residuals, simulate_trace
    from virtualaxis.diagnosis.trace import read_trace

    truth = truth_config(nominal_config(case.axis), case)
    paths = meta["files"]["holdout"] or meta["files"]["fit"]
    res = []
    for p in paths:
        td = TraceData.from_trace(read_trace(p, truth.axis.name))
        res.append(residuals(td, simulate_trace(truth, td, simulate or default_simulate)))
    return pooled_metrics(res)


def evaluate_case(meta: dict, report: dict, truth_metrics: dict | None = None) -> dict:
    """Compare the diagnosis with the truth. ``truth_metrics``: held-out metrics of the truth model
    (the floor: how far the RMSE can shrink at all)."""
    truth = list(meta["effects"])
    ranked = [e["name"] for e in report["effects"]]
    accepted = list(report["accepted"])
    if truth:
        top1 = bool(accepted) and accepted[0] in truth
        top2 = any(n in truth for n in (accepted[:2] if accepted else ranked[:2]))
        all_found = set(truth) <= set(accepted)
    else:
        top1 = top2 = all_found = not accepted
    rec: dict[str, dict] = {}
    for e in report["effects"]:
        if not e["accepted"] or e["name"] not in meta["truth_params"]:
            continue
        for pname, true_v in meta["truth_params"][e["name"]].items():
            vals = derived_values(e["name"], {k: v["value"] for k, v in e["params"].items()})
            if pname in vals and true_v:
                reported = e["params"].get(pname, {})
                determined = reported.get("determined", True)
                se = float(reported["stderr"]) if reported.get("stderr") is not None and determined else math.nan
                err = abs(vals[pname] - true_v)
                rec[f"{e['name']}.{pname}"] = {"true": true_v, "fitted": vals[pname], "rel_error": err / abs(true_v),
                                               "stderr": se, "determined": bool(determined),
                                               "error_in_stderr": err / se if se > 0 else math.nan}
    hold = report["baseline_heldout"] or report["baseline_fit"]
    fin = report["final"]["heldout"] or report["final"]["fit"]
    shrink = {ch: 1.0 - fin[ch]["rmse"] / hold[ch]["rmse"] for ch in fin if ch in hold and hold[ch]["rmse"] > 0}
    hyb = report.get("hybrid") or {}
    tm = truth_metrics or {}
    shrink_truth = {ch: 1.0 - tm[ch]["rmse"] / hold[ch]["rmse"] for ch in shrink if ch in tm}
    closed = {ch: (hold[ch]["rmse"] - fin[ch]["rmse"]) / (hold[ch]["rmse"] - tm[ch]["rmse"])
              for ch in shrink_truth if hold[ch]["rmse"] - tm[ch]["rmse"] > 0.05 * hold[ch]["rmse"]}
    return {"case": meta["case"], "axis": meta["axis"], "truth": truth, "accepted": accepted, "ranked": ranked[:4],
            "top1": top1, "top2": top2, "all_found": all_found, "false_positive": (not truth) and bool(accepted),
            "param_recovery": rec, "heldout_rmse_shrink": shrink, "heldout_rmse_shrink_truth_model": shrink_truth,
            "heldout_gap_closed": closed,
            "hybrid_model": hyb.get("model"), "seconds": report["timing"]["total_s"]}


#: how a bench diagnoses each case: ``cli`` runs ``virtualaxis diagnose`` in a subprocess, as a user does, and
#: reads the report.json it wrote; ``library`` calls :func:`~virtualaxis.diagnosis.pipeline.run_diagnosis`
DOORS = ("cli", "library")


class DiagnoseFailed(RuntimeError):
    """``virtualaxis diagnose`` exited with a non-zero status on a bench case."""

    def __init__(self, exit_code: int, message: str, log_path: Path):
        self.exit_code = exit_code
        self.message = message
        self.log_path = log_path
        super().__init__(f"virtualaxis diagnose exited with {exit_code}: {message} (log: {log_path})")


def diagnose_command(config: str | Path, fit: list, holdout: list, out_dir: str | Path, jobs: int,
                     hybrid: bool) -> list[str]:
    """The ``virtualaxis diagnose`` command line of a case (run with this interpreter)."""
    cmd = [sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(config),
           *[str(p) for p in fit]]
    if holdout:
        cmd += ["--holdout", *[str(p) for p in holdout]]
    cmd += ["--out", str(out_dir), "--force", "--jobs", str(jobs)]
    if not hybrid:
        cmd.append("--no-hybrid")
    return cmd


def diagnose_through_cli(config: str | Path, fit: list, holdout: list, out_dir: str | Path, jobs: int = 1,
                         hybrid: bool = True) -> dict:
    """Run ``virtualaxis diagnose`` on the case's files in a subprocess (no terminal: stdin closed, output
    captured) and return its report.json. The command, exit status, stdout and stderr go to
    ``<out_dir>.log``; a non-zero exit raises :class:`DiagnoseFailed` with the CLI's last stderr line."""
    import subprocess

    out_dir = Path(out_dir)
    cmd = diagnose_command(config, fit, holdout, out_dir, jobs, hybrid)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, check=False)
    wall_s = time.perf_counter() - t0
    log = out_dir.with_name(out_dir.name + ".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(f"$ {' '.join(cmd)}\nexit status {proc.returncode}, {wall_s:.1f} s\n--- stdout\n{proc.stdout}"
                   f"--- stderr\n{proc.stderr}", encoding="utf-8")
    if proc.returncode != 0:
        last = next((ln for ln in reversed(proc.stderr.splitlines()) if ln.strip()), "(no output)")
        raise DiagnoseFailed(proc.returncode, last, log)
    rep = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    rep["_door"] = {"door": "cli", "exit_code": proc.returncode, "wall_s": wall_s, "log": str(log)}
    return rep


def run_bench(out_dir: Path, seed: int = 0, case_names: list[str] | None = None, quick: bool = False,
              jobs: int = 1, simulate=None, progress=None, door: str = "cli") -> dict:
    """Generate the cases, diagnose each (``door``: see :data:`DOORS`; a custom ``simulate`` needs
    ``library``), evaluate; writes bench.json and per-case reports."""
    from virtualaxis.diagnosis.data import default_simulate
    from virtualaxis.diagnosis.fit import FitSettings
    from virtualaxis.diagnosis.pipeline import run_diagnosis, write_outputs

    cases = {c.name: c for c in all_cases()}
    names = case_names or (list(QUICK_CASES) if quick else list(cases))
    unknown = [n for n in names if n not in cases]
    if unknown:
        from virtualaxis.config.errors import InputError

        raise InputError("--cases", f"unknown case(s) {', '.join(unknown)}; known: {', '.join(cases)}")
    if door not in DOORS or (simulate is not None and door != "library"):
        raise ValueError(f"door must be one of {DOORS} (a custom simulate needs 'library'), got {door!r}")
    results = []
    t0 = time.perf_counter()
    for k, name in enumerate(names):
        case = cases[name]
        cdir = out_dir / name
        meta = generate_case(case, cdir, seed + k, quick)
        if door == "cli":
            rep = diagnose_through_cli(cdir / "nominal.toml", meta["files"]["fit"], meta["files"]["holdout"],
                                       cdir / "diagnosis", jobs=jobs, hybrid=not quick)
        else:
            cfg = load_axis_config(cdir / "nominal.toml")
            result = run_diagnosis(cfg, meta["files"]["fit"], meta["files"]["holdout"],
                                simulate=simulate or default_simulate, jobs=jobs, settings=FitSettings(),
                                hybrid=not quick)
            write_outputs(result, cdir / "diagnosis")
            rep = result.report
        ev = evaluate_case(meta, rep, truth_model_metrics(case, meta, simulate))
        ev["door"] = rep.get("_door", {"door": "library"})
        results.append(ev)
        if progress:
            progress(ev)
    summary = summarise(results)
    summary["seconds"] = time.perf_counter() - t0
    out = {"seed": seed, "quick": quick, "summary": summary, "cases": results}
    out_dir.mkdir(parents=True, exist_ok=True)
    from virtualaxis.diagnosis.report import report_json

    (out_dir / "bench.json").write_text(report_json(out), encoding="utf-8")
    return out


def rescore_bench(out_dir: Path, simulate=None) -> dict:
    """Score a finished bench again from its files (``CASE/truth.json``, ``CASE/diagnosis/report.json``) with
    the current scoring, without diagnosing again (only the truth model is simulated); rewrites bench.json."""
    from virtualaxis.diagnosis.report import report_json

    old = json.loads((out_dir / "bench.json").read_text(encoding="utf-8"))
    cases = {c.name: c for c in all_cases()}
    results = []
    for r in old["cases"]:
        cdir = out_dir / r["case"]
        meta = json.loads((cdir / "truth.json").read_text(encoding="utf-8"))
        rep = json.loads((cdir / "diagnosis" / "report.json").read_text(encoding="utf-8"))
        results.append(evaluate_case(meta, rep, truth_model_metrics(cases[r["case"]], meta, simulate)))
    summary = summarise(results)
    summary["seconds"] = old["summary"].get("seconds", math.nan)
    out = {"seed": old["seed"], "quick": old["quick"], "summary": summary, "cases": results}
    (out_dir / "bench.json").write_text(report_json(out), encoding="utf-8")
    return out


def summarise(results: list[dict]) -> dict:
    eff = [r for r in results if r["truth"]]
    clean = [r for r in results if not r["truth"]]
    recs = [v["rel_error"] for r in eff for v in r["param_recovery"].values()]
    zs = [v["error_in_stderr"] for r in eff for v in r["param_recovery"].values()
          if math.isfinite(v.get("error_in_stderr", math.nan))]
    shrink_per_effect: dict[str, list[float]] = {}
    for r in eff:
        pos = [v for ch, v in r["heldout_rmse_shrink"].items() if ch in ("pos_meas", "pos_fb", "motor_pos")]
        best = max(r["heldout_rmse_shrink"], key=r["heldout_rmse_shrink"].get) if r["heldout_rmse_shrink"] else ""
        val = r["heldout_rmse_shrink"][best] if best else 0.0
        truth_best = r.get("heldout_rmse_shrink_truth_model", {}).get(best, float("nan"))
        closed = r.get("heldout_gap_closed", {})
        shrink_per_effect[r["case"]] = [val, max(pos) if pos else float("nan"), truth_best,
                                        closed.get(best, float("nan"))]
    return {
        "n_effect_cases": len(eff),
        "n_clean_cases": len(clean),
        "top1_accuracy": float(np.mean([r["top1"] for r in eff])) if eff else float("nan"),
        "top2_accuracy": float(np.mean([r["top2"] for r in eff])) if eff else float("nan"),
        "all_effects_found": float(np.mean([r["all_found"] for r in eff])) if eff else float("nan"),
        "false_positive_rate": float(np.mean([r["false_positive"] for r in clean])) if clean else float("nan"),
        "param_rel_error_median": float(np.median(recs)) if recs else float("nan"),
        "param_within_15pct": float(np.mean([x <= 0.15 for x in recs])) if recs else float("nan"),
        # honesty of the reported uncertainty: of the parameters reported as determined, the share whose true
        # value lies within 2 standard errors; and how many were reported as not determined by the fit traces
        "param_within_2_stderr": float(np.mean([z <= 2.0 for z in zs])) if zs else float("nan"),
        "param_n_with_stderr": len(zs),
        "param_n_undetermined": sum(1 for r in eff for v in r["param_recovery"].values()
                                    if not v.get("determined", True)),
        "heldout_shrink_best_channel": {k: v[0] for k, v in shrink_per_effect.items()},
        "heldout_shrink_position": {k: v[1] for k, v in shrink_per_effect.items()},
        # on the best channel: the shrink the truth model itself would give, and the share of that
        # removable gap the diagnosis closed
        "heldout_shrink_truth_model": {k: v[2] for k, v in shrink_per_effect.items()},
        "heldout_gap_closed": {k: v[3] for k, v in shrink_per_effect.items()},
    }
