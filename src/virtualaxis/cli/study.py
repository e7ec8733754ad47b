"""``virtualaxis study kv-sweep|support-stiffness|feed-sweep|inverter``: the seed papers' studies (CSV + JSON +
PNG). The figures the papers report for their own axes (seed 004 for kv-sweep, seed 000 for feed-sweep) are printed
and plotted beside the results as those papers' axes' figures: on another axis they are a scale, not a target."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from virtualaxis.cli.common import add_config_argument, parse_float_list
from virtualaxis.cli.errors import CliError
from virtualaxis.cli.outputs import add_force_argument, check_output_dir, staged_dir

#: most sweep values one run takes (each is a simulation of seconds of motion or a modal analysis)
MAX_VALUES = 200


def register(sub) -> None:
    p = sub.add_parser("study", help="reproduce a seed study: kv-sweep, support-stiffness, feed-sweep, inverter")
    p.add_argument("name", choices=("kv-sweep", "support-stiffness", "feed-sweep", "inverter"))
    add_config_argument(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--values", default=None,
                   help="sweep values: kv [1/min] for kv-sweep, scales for support-stiffness, feeds [mm/min]")
    add_force_argument(p)
    p.set_defaults(func=run)


def _write_rows(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _value_range(name: str, cfg) -> tuple[float, float, str]:
    """The range of ``--values`` a study accepts: what the config itself may hold (config/bounds.py) once the
    value is applied, so a sweep value is refused naming ``--values``, not the config key it lands in."""
    from virtualaxis.config.bounds import BOUNDS

    if name == "kv-sweep":
        lo, hi = BOUNDS["control.kv_per_min"]
        return max(lo, 1e-3), hi, "1/min (control.kv_per_min's range)"
    if name == "support-stiffness":
        k = cfg.mechanics.support_axial_stiffness_n_per_m
        lo, hi = BOUNDS["mechanics.support_axial_stiffness_n_per_m"]
        return (lo / k if k > 0 else 1e-6), (hi / k if k > 0 else 1e6), "x the nominal support stiffness"
    vmax_mm_min = cfg.limits.max_velocity_m_s * 60e3  # feed-sweep, inverter: feeds [mm/min]
    return 1e-3, vmax_mm_min, "mm/min (up to limits.max_velocity_m_s)"


def run(args) -> int:
    from virtualaxis.config import load_axis_config

    cfg = load_axis_config(args.config)
    vals = parse_float_list(args.values, "--values") if args.values is not None else None
    if vals is not None:
        if len(vals) > MAX_VALUES:
            raise CliError(f"--values: {len(vals)} values; at most {MAX_VALUES}")
        bad = [v for v in vals if not v > 0]
        if bad:
            raise CliError(f"--values: {bad[0]:g} is not > 0 (kv [1/min], stiffness scales and feeds [mm/min] are "
                           "positive)")
        lo, hi, what = _value_range(args.name, cfg)
        bad = [v for v in vals if not lo <= v <= hi]
        if bad:
            raise CliError(f"--values: {bad[0]:g} is outside {lo:g} .. {hi:g} {what} for study {args.name}")
    stem = args.name.replace("-", "_")
    check_output_dir(args.out, args.force, (f"{stem}.csv", f"{stem}.json", f"{stem}*.png"), inputs=[args.config])
    with staged_dir(args.out) as stage:
        return _run(args, cfg, vals, stem, Path(stage))


def _run(args, cfg, vals, stem: str, out: Path) -> int:
    """Run the study, writing every file into ``out`` (the staging folder)."""
    from tqdm import tqdm

    from virtualaxis.studies import seeds
    from virtualaxis.studies.plots import plot_xy

    if args.name == "support-stiffness":
        rows = seeds.support_stiffness_study(cfg, None if vals is None else np.array(vals))
        doc = {"rows": rows, "paper": "seed 004 Fig. 10: first frequency rises with support stiffness k0_A"}
        plot_xy(out / f"{stem}.png", [r["support_scale"] for r in rows],
                {"first natural frequency": [r["first_natural_frequency_hz"] for r in rows]},
                "support stiffness / nominal", "frequency [Hz]", f"{cfg.axis.name}: nut at mid-stroke")
        f = [r["first_natural_frequency_hz"] for r in rows]
        print(f"first mode {min(f):.1f} .. {max(f):.1f} Hz over support scale {rows[0]['support_scale']:g}.."
              f"{rows[-1]['support_scale']:g}")
    elif args.name == "kv-sweep":
        kvs = None if vals is None else np.array(vals)
        n = len(kvs) if kvs is not None else 17
        with tqdm(total=n, desc="kv sweep", leave=False, disable=None) as bar:
            doc = seeds.kv_sweep_study(cfg, kvs, progress=bar.update)
        rows = doc["rows"]
        kv = [r["kv_per_min"] for r in rows]
        for key, unit, scale in (("energy_per_cycle_j", "J", 1), ("static_position_error_m", "um", 1e6),
                                 ("response_time_s", "s", 1), ("cost", "-", 1)):
            plot_xy(out / f"{stem}_{key}.png", kv, {key: [r[key] * scale for r in rows]}, "kv [1/min]",
                    f"{key} [{unit}]", f"{cfg.axis.name}")
        from virtualaxis.studies.plots import plot_kv_weight_sensitivity

        plot_kv_weight_sensitivity(out / f"{stem}_weights.png", doc["weight_sensitivity"], cfg.axis.name)
        ts = doc["timing_sensitivity"]
        plot_xy(out / f"{stem}_timing.png", [1e3 * d for d in ts["delays_s"]],
                {"optimum kv (equal weights)": ts["optimum_kv_per_min"]}, "error read at [ms] after the move",
                "optimum kv [1/min]", f"{cfg.axis.name}: when is the static error read?",
                paper={"seed 004's axis: 2725 1/min": ([0, 1e3 * ts["delays_s"][-1]], [ts["paper_kv_per_min"]] * 2)})
        inside = ts["delays_within_tolerance_s"]
        print("  error read d after the move (equal weights): optimum within 10 % of seed 004's for d = "
              + (", ".join(f"{1e3 * d:.0f}" for d in inside) + " ms" if inside else "none of 0..400 ms"))
        print(f"cost optimum at kv = {doc['optimum_kv_per_min']:g} 1/min (seed 004's axis: "
              f"{doc['paper_optimum_kv_per_min']:g}); "
              f"relative spans: {json.dumps({k: round(v, 3) for k, v in doc['relative_span'].items()})}")
        for name, r in doc["weight_sensitivity"]["readings"].items():
            lo, hi = r["optimum_range_kv_per_min"]
            print(f"  weights open ({name}): optimum {lo:g}..{hi:g}"
                  f" 1/min; {100 * r['share_of_weights_within_tolerance']:.0f} % of weight triples within 10 % of"
                  f" seed 004's; closest to equal weights: {r['closest_weights_within_tolerance']}")
    elif args.name == "inverter":
        rows = seeds.inverter_study(cfg, vals or (1000, 6000))
        doc = {"rows": rows, "paper": "seed 000 Fig. 6: SVPWM sector / dwell time / compare thresholds, six switches"}
        feeds = [r["feed_mm_min"] for r in rows]
        plot_xy(out / f"{stem}.png", feeds,
                {"averaged: RMS E": [r["averaged_rms_tracking_error_um"] for r in rows],
                 "switching (SVPWM): RMS E": [r["svpwm_rms_tracking_error_um"] for r in rows]},
                "feed [mm/min]", "tracking error [um]", f"{cfg.axis.name}: averaged vs switching inverter")
        plot_xy(out / f"{stem}_ripple.png", feeds,
                {"averaged": [r["averaged_current_ripple_rms_a"] for r in rows],
                 "switching (SVPWM)": [r["svpwm_current_ripple_rms_a"] for r in rows]},
                "feed [mm/min]", "i_q ripple within PWM periods, RMS [A]",
                f"{cfg.axis.name}: current ripple of the inverter models")
        for r in rows:
            print(f"F{r['feed_mm_min']:.0f}: ripple {r['svpwm_current_ripple_rms_a']:.3f} A RMS (switching) vs 0 "
                  f"(averaged); tracking RMS {r['averaged_rms_tracking_error_um']:.2f} / "
                  f"{r['svpwm_rms_tracking_error_um']:.2f} um; "
                  f"wall {r['averaged_wall_s']:.2f} / {r['svpwm_wall_s']:.2f} s")
    else:
        feeds = vals or [1000, 2000, 3000, 4000, 5000, 6000]
        with tqdm(total=len(feeds), desc="feed sweep", leave=False, disable=None) as bar:
            rows = seeds.feed_sweep_study(cfg, feeds, progress=bar.update)
        doc = {"rows": rows, "paper": "seed 000 Table 3; measured magnitude = analytical MAE / RE"}
        plot_xy(out / f"{stem}.png", [r["feed_mm_min"] for r in rows],
                {"ours: max |E|": [r["max_abs_tracking_error_um"] for r in rows],
                 "ours: RMS E": [r["rms_tracking_error_um"] for r in rows]},
                "feed [mm/min]", "tracking error [um]", f"{cfg.axis.name}: 100 mm sine",
                paper={"seed 000's axis: measured |E| (MAE/RE)": ([r["feed_mm_min"] for r in rows],
                                                       [r["paper_measured_magnitude_um"] for r in rows])})
        for r in rows:
            print(f"F{r['feed_mm_min']:.0f}: max {r['max_abs_tracking_error_um']:.1f} um, RMS "
                  f"{r['rms_tracking_error_um']:.1f} um (seed 000's axis measured "
                  f"~{r['paper_measured_magnitude_um']:.0f} um)")
    _write_rows(out / f"{stem}.csv", doc["rows"])
    (out / f"{stem}.json").write_text(json.dumps({"config": str(args.config), **doc}, indent=2))
    return 0
