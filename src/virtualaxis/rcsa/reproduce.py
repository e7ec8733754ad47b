"""Side-by-side reproduction of seed 002 Tables 1, 4, 6, 7 (prediction with the paper's parameters) and
Tables 5, 8, 9 (our own single- vs multi-position identification on the paper's measured data).

``python -m virtualaxis.rcsa.reproduce --config configs/seed002-usst.toml --out docs/rcsa-reproduction``
writes ``<out>.md`` and ``<out>.json`` (and the FRF figures under docs/figures/rcsa/).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from virtualaxis.config import load_axis_config
from virtualaxis.rcsa import paper
from virtualaxis.rcsa.consistency import consistency_report
from virtualaxis.rcsa.consistency import figures as consistency_figures
from virtualaxis.rcsa.fe_shaft import fe_natural_frequencies_hz
from virtualaxis.rcsa.identify import identify_joints, overall_error, predict_modes, relative_errors
from virtualaxis.rcsa.params import JOINT_SYMBOLS, JOINT_UNITS, JointParams, RcsaModel, rcsa_model_from_config

LABELS = ("l1", "l2", "l3", "l4", "l5", "l6")


def undamped(model: RcsaModel) -> RcsaModel:
    """The same model with every damper removed (natural frequencies = poles of h_6a6a)."""
    j = model.joints
    zero = JointParams(j.k_al, j.k_ar, j.k_n, j.k_m, 0.0, 0.0, 0.0, 0.0)
    return replace(model, joints=zero, parts=replace(model.parts, rotor_holding_damping_nm_s_per_rad=0.0))


def _fmt(v: float, digits: int = 0) -> str:
    return "—" if not math.isfinite(v) else f"{v:.{digits}f}"


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{100 * v:.2f} %"


def nan_to_none(obj: object) -> object:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [nan_to_none(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return nan_to_none(obj.tolist())
    return obj


def _mean_finite(rows: list[dict], key: str = "ours_damped_overall_error") -> float:
    """Mean eq. 27 error over the positions where every measured mode was predicted (NaN if none)."""
    vals = [r[key] for r in rows if math.isfinite(r[key])]
    return float(np.mean(vals)) if vals else float("nan")


def _missing(rows: list[dict]) -> int:
    """How many measured modes the prediction does not show (no peak in the band)."""
    return int(
        sum(np.sum(np.isfinite(r["measured_hz"]) & ~np.isfinite(r["ours_damped_peak_hz"])) for r in rows)
    )


def prediction_rows(
    model: RcsaModel, joints: JointParams, labels: tuple[str, ...], paper_key: str | None
) -> list[dict]:
    """Per position: measured, paper's prediction, ours (damped FRF peak), ours (undamped), errors."""
    rows = []
    damped = predict_modes(model, [paper.POSITIONS_M[x] for x in labels], joints)
    und = predict_modes(undamped(model.with_joints(joints)), [paper.POSITIONS_M[x] for x in labels])
    for lab, d, u in zip(labels, damped, und, strict=True):
        meas = np.array(paper.MEASURED_FREQUENCIES_HZ[lab])
        theirs = np.array(paper.PAPER_PREDICTED_HZ.get(paper_key or "", {}).get(lab, (np.nan,) * 4))
        rows.append(
            {
                "position": lab,
                "position_m": paper.POSITIONS_M[lab],
                "measured_hz": meas,
                "paper_predicted_hz": theirs,
                "ours_damped_peak_hz": d.natural_frequencies_hz,
                "ours_damped_amplitude_m_per_n": d.amplitudes_m_per_n,
                "ours_undamped_hz": u.natural_frequencies_hz,
                "paper_error": relative_errors(theirs, meas),
                "ours_damped_error": relative_errors(d.natural_frequencies_hz, meas),
                "ours_undamped_error": relative_errors(u.natural_frequencies_hz, meas),
                "ours_damped_overall_error": overall_error(d.natural_frequencies_hz, meas),
                "ours_undamped_overall_error": overall_error(u.natural_frequencies_hz, meas),
                # the paper prints its predictions in whole Hz and computes its errors from those integers
                # (Table 4, l2: 549 vs 536 -> 2.43 %, 24 vs 24 -> 0.00 %); the same convention for ours:
                "ours_damped_overall_error_whole_hz": overall_error(np.round(d.natural_frequencies_hz), meas),
            }
        )
    return rows


def prediction_table_md(rows: list[dict]) -> str:
    out = [
        "| position | row | 1st | 2nd | 3rd | 4th | overall (eq. 27) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lab = f"{r['position']} ({r['position_m']:g} m)"
        out.append(f"| {lab} | measured | " + " | ".join(_fmt(v) for v in r["measured_hz"]) + " | |")
        if np.any(np.isfinite(r["paper_predicted_hz"])):
            err = overall_error(r["paper_predicted_hz"], r["measured_hz"])
            out.append(
                "| | paper predicted | "
                + " | ".join(_fmt(v) for v in r["paper_predicted_hz"])
                + f" | {_pct(err)} |"
            )
            out.append("| | paper error | " + " | ".join(_pct(v) for v in r["paper_error"]) + " | |")
        out.append(
            "| | ours, FRF peak | "
            + " | ".join(_fmt(v, 1) for v in r["ours_damped_peak_hz"])
            + f" | {_pct(r['ours_damped_overall_error'])} |"
        )
        out.append(
            "| | ours, FRF peak error | " + " | ".join(_pct(v) for v in r["ours_damped_error"]) + " | |"
        )
        out.append(
            "| | ours, undamped | "
            + " | ".join(_fmt(v, 1) for v in r["ours_undamped_hz"])
            + f" | {_pct(r['ours_undamped_overall_error'])} |"
        )
        out.append(
            "| | ours, undamped error | " + " | ".join(_pct(v) for v in r["ours_undamped_error"]) + " | |"
        )
    return "\n".join(out)


def joints_table_md(columns: dict[str, JointParams]) -> str:
    head = "| parameter | " + " | ".join(columns) + " | unit |"
    out = [head, "|---" * (len(columns) + 2) + "|"]
    for sym, unit in zip(JOINT_SYMBOLS, JOINT_UNITS, strict=True):
        out.append(
            f"| {sym} | " + " | ".join(f"{getattr(j, sym):.3g}" for j in columns.values()) + f" | {unit} |"
        )
    return "\n".join(out)


def held_out_md(rows: dict[str, list[dict]]) -> str:
    out = [
        "| identification | position | measured | ours predicted | ours error | ours overall"
        " | ours overall, whole Hz | paper overall |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, rs in rows.items():
        for r in rs:
            paper_overall = paper.PAPER_OVERALL_ERROR.get(key, {}).get(r["position"], float("nan"))
            out.append(
                f"| {key} | {r['position']} | "
                + ", ".join(_fmt(v) for v in r["measured_hz"])
                + " | "
                + ", ".join(_fmt(v, 1) for v in r["ours_damped_peak_hz"])
                + " | "
                + ", ".join(_pct(v) for v in r["ours_damped_error"])
                + f" | {_pct(r['ours_damped_overall_error'])} | {_pct(r['ours_damped_overall_error_whole_hz'])}"
                + f" | {_pct(paper_overall)} |"
            )
    return "\n".join(out)


def fe_cross_check(model: RcsaModel, labels: tuple[str, ...] = LABELS) -> list[dict]:
    """Undamped natural frequencies in the mode bands: RCSA poles vs the FE eigenvalues (nearest)."""
    rows = []
    und = undamped(model)
    for lab in labels:
        pos = paper.POSITIONS_M[lab]
        rcsa = predict_modes(und, [pos])[0].natural_frequencies_hz
        fe = fe_natural_frequencies_hz(model, pos)
        nearest = np.array([fe[np.argmin(np.abs(fe - f))] if math.isfinite(f) else np.nan for f in rcsa])
        rows.append(
            {
                "position": lab,
                "position_m": pos,
                "rcsa_hz": rcsa,
                "fe_hz": nearest,
                "fe_all_below_1khz_hz": fe[(fe > 1.0) & (fe < 1000.0)],
                "relative_difference": relative_errors(rcsa, nearest),
            }
        )
    return rows


def run(config: str, out: Path, figures: Path | None, generations: int, seed: int) -> dict:
    cfg = load_axis_config(config)
    model = rcsa_model_from_config(cfg)
    ident = model.identification
    if ident is None:
        raise SystemExit(f"{config}: [rcsa.identification] is needed for the reproduction")
    report: dict = {"config": config}
    # 1. prediction with the paper's parameters
    # the paper's joints as the config reads them: Table 3 from [rcsa.joints] (k_m printed 5.53e3 read as N m/rev,
    # docs/rcsa-reproduction.md), Table 5 with the same reading of its k_m
    km_factor = model.joints.k_m / paper.TABLE3_MULTI_POSITION.k_m
    report["k_m_reading_factor"] = km_factor
    multi_rows = prediction_rows(model, model.joints, LABELS, "multi")
    t6 = {
        "l3-single (Table 5)": prediction_rows(
            model, replace(paper.TABLE5_L3_SINGLE, k_m=paper.TABLE5_L3_SINGLE.k_m * km_factor), ("l3",), "l3"),
        "l5-single (Table 5)": prediction_rows(
            model, replace(paper.TABLE5_L5_SINGLE, k_m=paper.TABLE5_L5_SINGLE.k_m * km_factor), ("l5",), "l5"),
    }
    report["table3_prediction"] = multi_rows
    report["tables_6_7_single_parameters"] = t6
    report["fe_cross_check"] = fe_cross_check(model)
    report["consistency"] = consistency_report(model)
    # 2. our identification on the paper's measured data (Tables 1/2), single vs multi, with the
    #    amplitude terms of eq. 26 (as the paper) and with the frequency terms only
    runs = {"multi": ("l1", "l3", "l5"), "l3": ("l3",), "l5": ("l5",)}
    held_out = ("l2", "l4", "l6")
    report["variants"] = {}
    identified_by_variant: dict[str, dict[str, JointParams]] = {}
    variants = (
        ("eq26_as_printed_amplitude_weight_1", 1.0),
        (f"amplitude_weight_{ident.amplitude_weight:g}_from_config", ident.amplitude_weight),
        ("frequencies_only", 0.0),
    )
    for variant, weight in variants:
        identified: dict[str, JointParams] = {}
        timing = {}
        for key, labels in runs.items():
            t0 = time.perf_counter()
            res = identify_joints(
                model,
                paper.measured_modes(labels),
                lower=ident.lower,
                upper=ident.upper,
                population_per_parameter=ident.population_per_parameter,
                generations=generations,
                seed=seed,
                workers=ident.workers,
                amplitude_weight=weight,
            )
            timing[key] = {
                "wall_time_s": time.perf_counter() - t0,
                "objective": res.objective,
                "objective_evaluations": res.objective_evaluations,
            }
            identified[key] = res.joints
        ours_held = {k: prediction_rows(model, j, held_out, k) for k, j in identified.items()}
        report["variants"][variant] = {
            "identification": {
                k: {"train_positions": runs[k], "joints": identified[k].as_dict(), **timing[k]} for k in runs
            },
            "held_out": ours_held,
            "train_fit": {k: prediction_rows(model, j, runs[k], k) for k, j in identified.items()},
            "held_out_mean_overall_error": {k: _mean_finite(rs) for k, rs in ours_held.items()},
            "held_out_mean_overall_error_whole_hz": {
                k: _mean_finite(rs, "ours_damped_overall_error_whole_hz") for k, rs in ours_held.items()
            },
            "held_out_modes_not_predicted": {k: _missing(rs) for k, rs in ours_held.items()},
        }
        identified_by_variant[variant] = identified
    if figures is not None:
        consistency_figures(model, report["consistency"], figures)
        config_variant = variants[1][0]
        _figures(model, identified_by_variant[config_variant], figures, config_variant)
    _write(out, report, generations, seed)
    return report


def _figures(model: RcsaModel, identified: dict[str, JointParams], figures: Path, variant: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from virtualaxis.rcsa.receptance import table_frf

    figures.mkdir(parents=True, exist_ok=True)
    f = np.geomspace(5.0, 1000.0, 4000)
    h = np.empty(f.size, dtype=np.complex128)
    fig, ax = plt.subplots(figsize=(8, 5))
    for lab in LABELS:
        table_frf(f, paper.POSITIONS_M[lab], model.parameter_vector(), h)
        ax.loglog(f, np.abs(h), label=f"{lab} = {paper.POSITIONS_M[lab]:g} m")
    for b in model.mode_bands_hz:
        ax.axvspan(b[0], b[1], color="0.9", zorder=0)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("|h_6a6a| [m/N]")
    ax.set_title("RCSA table FRF with the config's Table 3 joints (grey: mode bands)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(figures / "frf_table3_positions.png", dpi=110)
    plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    for ax, lab in zip(axes, ("l2", "l4", "l6"), strict=True):
        for key, j in identified.items():
            table_frf(f, paper.POSITIONS_M[lab], model.parameter_vector(j), h)
            ax.loglog(f, np.abs(h), label=f"{key} identification")
        for fm in paper.MEASURED_FREQUENCIES_HZ[lab]:
            if math.isfinite(fm):
                ax.axvline(fm, color="k", ls=":", lw=0.8)
        ax.set_title(f"held out {lab} = {paper.POSITIONS_M[lab]:g} m (dotted: measured)")
        ax.set_xlabel("frequency [Hz]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("|h_6a6a| [m/N]")
    axes[0].legend()
    fig.suptitle(f"joints identified on the paper's Tables 1/2 ({variant})")
    fig.tight_layout()
    fig.savefig(figures / "frf_held_out_single_vs_multi.png", dpi=110)
    plt.close(fig)


def _write(out: Path, report: dict, generations: int, seed: int) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(nan_to_none(report), indent=1))
    md = [
        "# Seed 002 reproduction tables (generated)",
        "",
        "Generated by `python -m virtualaxis.rcsa.reproduce --config "
        + report["config"]
        + f" --out {out} --generations {generations} --seed {seed}`;"
        " the JSON beside this file holds every number.",
        "'ours, FRF peak' = peak of the damped h_6a6a in the mode band (— = no peak found there, the",
        "paper's convention at l4); 'ours, undamped' = the pole with all dampers removed.",
        "",
        "## Tables 1 and 4: prediction with the paper's Table 3 joints at l1..l6",
        "",
        f"Joints of the config's [rcsa.joints]: Table 3 with k_m read as N m/rev (x {report['k_m_reading_factor']:.4f},"
        " see the section at the end); Table 5's k_m read the same way.",
        "",
        "Paper predictions exist for l2, l4, l6 (Table 4) and l3, l5 (Tables 6, 7, multi-position rows).",
        "",
        prediction_table_md(report["table3_prediction"]),
        "",
        "## Tables 6 and 7: the paper's single-position joints at their own position",
        "",
    ]
    for name, rows in report["tables_6_7_single_parameters"].items():
        md += [f"### {name}", "", prediction_table_md(rows), ""]
    md += [
        "## Cross-check: RCSA vs independent FE model (undamped, Table 3 joints)",
        "",
        "| position | RCSA [Hz] | FE nearest [Hz] | max difference | all FE modes 1..1000 Hz |",
        "|---|---|---|---|---|",
    ]
    for r in report["fe_cross_check"]:
        md.append(
            f"| {r['position']} | "
            + ", ".join(_fmt(v, 2) for v in r["rcsa_hz"])
            + " | "
            + ", ".join(_fmt(v, 2) for v in r["fe_hz"])
            + f" | {_pct(float(np.nanmax(r['relative_difference'])))} | "
            + ", ".join(f"{v:.1f}" for v in r["fe_all_below_1khz_hz"])
            + " |"
        )
    for variant, v in report["variants"].items():
        ids = {k: JointParams(**d["joints"]) for k, d in v["identification"].items()}
        md += [
            "",
            f"## Table 5 ({variant}): our identification on the paper's measured data",
            "",
            joints_table_md(
                {
                    "paper l3": paper.TABLE5_L3_SINGLE,
                    "ours l3": ids["l3"],
                    "paper l5": paper.TABLE5_L5_SINGLE,
                    "ours l5": ids["l5"],
                    "paper multi": paper.TABLE3_MULTI_POSITION,
                    "ours multi": ids["multi"],
                }
            ),
            "",
            "| run | train positions | objective eq. 26 | evaluations | wall time |",
            "|---|---|---|---|---|",
        ]
        for k, d in v["identification"].items():
            md.append(
                f"| {k} | {', '.join(d['train_positions'])} | {d['objective']:.4f}"
                f" | {d['objective_evaluations']}"
                f" | {d['wall_time_s']:.1f} s |"
            )
        md += [
            "",
            f"## Tables 4, 8, 9 ({variant}): held-out positions l2, l4, l6",
            "",
            held_out_md(v["held_out"]),
            "",
            "Mean overall error (eq. 27) over the held-out positions where every measured mode was"
            " predicted: "
            + ", ".join(f"{k}: {_pct(e)}" for k, e in v["held_out_mean_overall_error"].items())
            + "; with our predictions rounded to whole Hz as the paper prints and scores its own: "
            + ", ".join(f"{k}: {_pct(e)}" for k, e in v["held_out_mean_overall_error_whole_hz"].items())
            + " (paper, multi: 2.43 %)"
            + "; measured held-out modes with no predicted peak: "
            + ", ".join(f"{k}: {n}" for k, n in v["held_out_modes_not_predicted"].items()),
        ]
    if "consistency" in report:
        from virtualaxis.rcsa.consistency import markdown

        md += ["", markdown(report["consistency"])]
    out.with_suffix(".md").write_text("\n".join(md) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/seed002-usst.toml")
    ap.add_argument("--out", default="docs/rcsa-reproduction")
    ap.add_argument("--figures", default="docs/figures/rcsa")
    ap.add_argument("--generations", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    run(a.config, Path(a.out), Path(a.figures) if a.figures else None, a.generations, a.seed)
    print(f"wrote {a.out}.md and {a.out}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
