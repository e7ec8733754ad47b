"""The whole gap bench.

``--suite reference`` (default): the independent reference axis' cases (``virtualaxis.refaxis``, written apart
from the diagnosed model; the bench's acceptance figures): right effect first, nothing accepted on clean
cases, no accepted effect outside the truth, main parameter within 15 %, held-out RMSE shrink >= 60 % on the
effect's channel; writes DIR/reference.json. ``--suite own``: our own simulator's cases (second column): top-1 /
top-2, false positives, parameter recovery, held-out shrink; writes DIR/bench.json.

    python benchmarks/bench_gap.py --out /tmp/gap_ref [--suite reference] [--seed 0] [--jobs 2] [--quick] [--cases a,b]
    python benchmarks/bench_gap.py --out /tmp/gap_bench --suite own [--quick] [--cases a,b]
    python benchmarks/bench_gap.py --out /tmp/gap_bench --suite own --rescore   # score a finished bench again
"""

from __future__ import annotations

import argparse
import math
import platform
import subprocess
import time
from pathlib import Path

from virtualaxis.diagnosis.bench import rescore_bench, run_bench


def _cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        model = next((ln.split(":", 1)[1].strip() for ln in out.splitlines() if ln.startswith("Model name")), "")
    except OSError:
        model = platform.processor()
    import os

    return f"{os.cpu_count()} cores, {model}"


def _se(v: dict) -> str:
    if not v.get("determined", True):
        return "not determined"
    se = v.get("stderr")
    return "-" if se is None or math.isnan(se) else f"{se:.3g}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/gap_bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--cases", default=None)
    ap.add_argument("--rescore", action="store_true",
                    help="score the bench in --out again, without diagnosing (reference: every case scored there)")
    ap.add_argument("--suite", choices=("reference", "own"), default="reference")
    ap.add_argument("--table", action="store_true", help="reference: also print the per-case markdown table")
    ap.add_argument("--door", choices=("cli", "library"), default="cli",
                    help="cli (default): each case through 'virtualaxis diagnose' in a subprocess; library: "
                    "the diagnosis called in this process")
    a = ap.parse_args()
    names = a.cases.split(",") if a.cases else None
    t0 = time.perf_counter()
    if a.suite == "reference":
        reference(a, names, t0)
        return

    def progress(ev: dict) -> None:
        rec = "; ".join(f"{k} {v['fitted']:.4g} ± {_se({'stderr': v['stderr'], 'determined': v['stderr'] is not None})}"
                        f" (true {v['true']:.4g}, {100 * v['rel_error']:.1f} %)"
                        for k, v in ev["param_recovery"].items())
        pos = ev["heldout_rmse_shrink"].get("pos_meas", float("nan"))
        print(f"{ev['case']:20s} truth={'+'.join(ev['truth']) or '-':30s} found={'+'.join(ev['accepted']) or '-':30s}"
              f" top1={int(ev['top1'])} pos_meas held-out RMSE -{100 * pos:.0f} % | {rec} | {ev['seconds']:.0f} s",
              flush=True)

    if a.rescore:
        out = rescore_bench(Path(a.out))
        for ev in out["cases"]:
            progress(ev)
    else:
        out = run_bench(Path(a.out), seed=a.seed, case_names=names, quick=a.quick, jobs=a.jobs, progress=progress,
                        door=a.door)
    s = out["summary"]
    print(f"\nmachine: {_cpu()}; wall time {time.perf_counter() - t0:.0f} s")
    print(f"effect cases {s['n_effect_cases']}, clean cases {s['n_clean_cases']}")
    print(f"top-1 accuracy {100 * s['top1_accuracy']:.0f} %   top-2 accuracy {100 * s['top2_accuracy']:.0f} %   "
          f"all withheld effects found {100 * s['all_effects_found']:.0f} %")
    print(f"false-positive rate on clean cases {100 * s['false_positive_rate']:.0f} %")
    med = s["param_rel_error_median"]
    print(f"parameter recovery: median relative error {100 * med:.1f} %, within 15 %: "
          f"{100 * s['param_within_15pct']:.0f} %" if not math.isnan(med) else "parameter recovery: -")
    if s.get("param_n_with_stderr"):
        print(f"reported uncertainty: true value within 2 standard errors for {100 * s['param_within_2_stderr']:.0f} % "
              f"of {s['param_n_with_stderr']} parameters; {s['param_n_undetermined']} reported as not determined "
              "by the fit traces")
    print("held-out RMSE shrink per case: best channel / pos_meas / truth model on the best channel (the noise")
    print("floor's limit) / share of the removable gap closed on the best channel:")
    for k, v in s["heldout_shrink_best_channel"].items():
        print(f"  {k:24s} {100 * v:6.1f} %  {100 * s['heldout_shrink_position'][k]:6.1f} %  "
              f"{100 * s['heldout_shrink_truth_model'][k]:6.1f} %  {100 * s['heldout_gap_closed'][k]:6.1f} %")
    print(f"wrote {Path(a.out) / 'bench.json'}")


def reference(a, names, t0: float) -> None:
    from virtualaxis.gapbench.reference import run_reference_bench

    def progress(ev: dict) -> None:
        if ev.get("failed"):
            print(f"{ev['case']:42s} FAILED: virtualaxis diagnose exit {ev['exit_code']}: {ev['error']}", flush=True)
            return
        rec = "; ".join(f"{k} {v['fitted']:.4g} ± {_se(v)} (true {v['true']:.4g}, {100 * v['rel_error']:.1f} %)"
                        for k, v in ev["param_recovery"].items())
        ceil = ev["truth_model_ceiling"]
        print(f"{ev['case']:42s} truth={'+'.join(ev['truth']) or '-':36s} found={'+'.join(ev['answer']) or '-':36s}"
              f" first={int(ev['top1'])} outside={','.join(ev['outside_truth']) or '-'} | {rec or '-'} | "
              f"{ev['effect_channel']} held-out RMSE -{100 * ev['shrink_on_effect_channel']:.0f} %"
              + (f" (truth model {100 * ceil:.0f} %)" if ceil == ceil else "")
              + (f" | {ev['model_form_mismatch']}" if ev["model_form_mismatch"] else "")
              + f" | {ev['seconds']:.0f} s", flush=True)

    if a.rescore:  # every case scored in --out so far (chunks of one run)
        from virtualaxis.gapbench.reference import rescore_reference

        out = rescore_reference(Path(a.out), a.seed, a.quick)
        for ev in out["cases"]:
            progress(ev)
    else:
        out = run_reference_bench(Path(a.out), seed=a.seed, case_names=names, quick=a.quick, jobs=a.jobs,
                                  progress=progress, door=a.door)
    s = out["summary"]

    def pct(x) -> str:
        return "-" if x != x else f"{100 * x:.0f} %"

    print(f"\nmachine: {_cpu()}; wall time {time.perf_counter() - t0:.0f} s; reference axis cases: "
          f"{s['n_effect_cases']} with withheld effects, {s['n_clean_cases']} clean")
    print(f"right effect first {pct(s['right_effect_first'])} (>= 90 %)   clean cases with nothing accepted "
          f"{pct(s['clean_nothing_accepted'])} (100 %)   no accepted effect outside the truth "
          f"{pct(s['none_outside_truth'])} (>= 90 %)")
    print(f"main parameter within 15 %: {pct(s['param_within_15pct'])} (>= 90 %; median error "
          f"{pct(s['param_rel_error_median'])})   held-out RMSE shrink >= 60 % on the effect's channel: "
          f"{pct(s['shrink_ge_60pct'])}")
    if s.get("param_n_with_stderr"):
        print(f"reported uncertainty: true value within 2 standard errors for {pct(s['param_within_2_stderr'])} of "
              f"{s['param_n_with_stderr']} found main parameters; {s['param_n_undetermined']} reported as not "
              "determined by the fit traces")
    for st, v in s.get("by_structure", {}).items():
        print(f"  {st:12s} ({v['n_effect_cases']} + {v['n_clean_cases']} clean): first {pct(v['right_effect_first'])}, "
              f"clean {pct(v['clean_nothing_accepted'])}, none outside {pct(v['none_outside_truth'])}, "
              f"param within 15 % {pct(v['param_within_15pct'])}, shrink >= 60 % {pct(v['shrink_ge_60pct'])}")
    if out.get("failed"):
        print(f"not scored ({len(out['failed'])}): virtualaxis diagnose failed on "
              + "; ".join(f"{f['case']} (exit {f['exit_code']}: {f['error']})" for f in out["failed"]))
    print(f"door: {a.door} ({'virtualaxis diagnose in a subprocess per case' if a.door == 'cli' else 'in-process'})")
    if a.table:
        print(markdown_table(out["cases"]))
    print(f"wrote {Path(a.out) / 'reference.json'}")


def markdown_table(cases: list[dict]) -> str:
    """Per-case table of a reference bench run (docs/diagnosis.md)."""
    rows = ["| case | withheld | found (first first) | right first | main parameter (fitted ± SE, true, error) | "
            "held-out shrink (channel) |", "|---|---|---|---|---|---|"]
    for ev in cases:
        rec = "; ".join(
            f"{k.split('.', 1)[1]} {v['fitted']:.4g}"
            + (f" ± {v['stderr']:.2g}" if v.get("stderr") is not None else " (not determined)")
            + f" (true {v['true']:.4g}, {100 * v['rel_error']:.0f} %)" for k, v in ev["param_recovery"].items())
        miss = ", ".join(ev.get("params_not_found", []))
        sh = ev["shrink_on_effect_channel"]
        shrink = "-" if sh is None or sh != sh else f"{100 * sh:.0f} % ({ev['effect_channel']})"
        found = " + ".join(ev["answer"]) or "no significant effect"
        if ev.get("model_form_mismatch"):
            found += " + model-form mismatch"
        rows.append(f"| {ev['case']} | {'+'.join(ev['truth']) or '-'} | {found} | {'yes' if ev['top1'] else 'no'} | "
                    f"{rec or ('not found: ' + miss if miss else '-')} | {shrink} |")
    return "\n".join(rows)


if __name__ == "__main__":
    main()
