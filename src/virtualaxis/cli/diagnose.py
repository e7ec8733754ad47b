"""``virtualaxis diagnose``: where the sim-to-real gap lies, which unmodelled effect causes it, how far
it shrinks. Writes DIR/report.json, DIR/report.html and DIR/calibrated.toml."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from virtualaxis.cli.outputs import add_force_argument, check_output_dir, staged_dir
from virtualaxis.config import load_axis_config

#: files written into --out
OUT_NAMES = ("report.json", "report.html", "calibrated.toml")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "diagnose",
        help="diagnose the sim-to-real gap of measured traces",
        description="Simulate the nominal axis on each trace's command, locate the residual, fit candidate "
        "unmodelled effects (judged on held-out traces) and a data-driven residual model.",
    )
    p.add_argument("--config", required=True, help="axis config (TOML)")
    p.add_argument("traces", nargs="+", metavar="TRACE.csv", help="fit traces (trace-format CSV)")
    p.add_argument("--holdout", nargs="+", default=[], metavar="TRACE.csv",
                   help="held-out traces (default: split by condition, fit on the slowest and fastest)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--jobs", type=int, default=None, help="local worker processes for candidate fits (default 2; "
                   "at most 2 per CPU and what the available memory holds)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="run candidate fits on a running Dask cluster (needs dask[distributed])")
    p.add_argument("--effects", default=None, help="comma-separated subset of the effect library")
    p.add_argument("--method", choices=("gn", "lsq", "de"), default="gn",
                   help="refinement of each candidate: bounded Gauss-Newton with a secant Jacobian (default), "
                   "scipy least_squares, or differential evolution (slow)")
    p.add_argument("--no-hybrid", action="store_true", help="skip the data-driven residual models")
    add_force_argument(p)
    p.set_defaults(func=run)



def _effect_names(text: str | None) -> list[str] | None:
    """``--effects`` checked before any work: not empty, no empty item, known names, none twice."""
    from virtualaxis.cli.main import CliError
    from virtualaxis.diagnosis.effects import EFFECTS

    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if not text.strip() or "" in names:
        raise CliError(f"--effects: empty effect name in {text!r}; give comma-separated names of the library "
                       f"({', '.join(EFFECTS)}) or leave the option out for all")
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise CliError(f"--effects: unknown effect(s) {', '.join(unknown)}; known: {', '.join(EFFECTS)}")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CliError(f"--effects: {', '.join(dup)} given twice")
    return names


class StageProgress:
    """Renders the diagnosis' :class:`~virtualaxis.diagnosis.progress.ProgressEvent` s on stderr: on a terminal
    a bar per fitting stage (advancing per candidate); otherwise (a CI log, a pipe) one line per stage and
    nothing per candidate. The lines of the checking stages (reading the traces, the controller check, the
    baseline and its plausibility, locating the residual) are shown once the first fit starts: an input these
    stages refuse gets its ``error:`` line alone."""

    #: stages that may still refuse the input
    CHECKING = ("read", "controller_check", "baseline", "localise")

    def __init__(self, stream=None) -> None:
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.bar = None
        self.pending: list[str] = []

    def __call__(self, ev) -> None:
        if ev.kind == "start" and ev.stage in self.CHECKING:
            self.pending.append(f"diagnose: {ev.describe()}")
            return
        if self.pending:
            print("\n".join(self.pending), file=self.stream, flush=True)
            self.pending.clear()
        if not self.tty:
            if ev.kind == "start":
                print(f"diagnose: {ev.describe()}", file=self.stream, flush=True)
            return
        from tqdm import tqdm

        if ev.kind == "start":
            self.close()
            if ev.total:
                # a pty that reports no size (0 x 0: script, docker -t) would hide the bar: 80 x 24 then
                cols, rows = shutil.get_terminal_size()
                self.bar = tqdm(total=ev.total, desc=ev.describe(), unit="fit", leave=False, file=self.stream,
                                ncols=cols, nrows=rows)
            else:
                print(f"diagnose: {ev.describe()}", file=self.stream, flush=True)
        elif self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(ev.effect)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run(args: argparse.Namespace) -> int:
    from virtualaxis.cli.common import check_jobs
    from virtualaxis.cli.main import CliError
    from virtualaxis.diagnosis.fit import FitSettings
    from virtualaxis.diagnosis.pipeline import run_diagnosis, write_outputs
    from virtualaxis.diagnosis.report import verdict_text

    args.jobs = check_jobs(args.jobs)
    names = _effect_names(args.effects)
    if args.scheduler is not None:
        import re

        m = re.fullmatch(r"(tcp|tls|inproc|ucx)://([^:/\s]+|\[[0-9a-fA-F:]+\]):(\d{1,5})", args.scheduler.strip())
        if not m or not 1 <= int(m.group(3)) <= 65535:
            raise CliError(f"--scheduler: {args.scheduler!r} is not an address tcp://HOST:PORT (port 1..65535)")
    cfg = load_axis_config(args.config)
    inputs = [args.config, *args.traces, *args.holdout]
    check_output_dir(args.out, args.force, OUT_NAMES, inputs=inputs)
    progress = StageProgress()
    try:
        result = run_diagnosis(cfg, args.traces, args.holdout, jobs=args.jobs, scheduler=args.scheduler,
                               settings=FitSettings(method=args.method), effect_names=names, progress=progress,
                               hybrid=not args.no_hybrid)
    except ImportError as exc:
        if args.scheduler and "dask" in str(exc):
            raise CliError(str(exc)) from None
        raise
    except ConnectionError as exc:
        raise CliError(str(exc)) from None
    finally:
        progress.close()
    with staged_dir(args.out) as stage:
        staged = write_outputs(result, stage)
    report = result.report
    paths = {k: Path(args.out) / Path(v).name for k, v in staged.items()}
    for w in report.get("warnings", []):  # repairs, plausibility findings, split notes: never silent
        print(f"warning: {w.replace('plausibility: ', '')}", file=sys.stderr)
    print(f"conclusion: {report['conclusion']}")
    for line in (report["headline"] if report["accepted"] else []):
        print(f"  {line}")
    on = _judged_on("holdout" if any(t["role"] == "holdout" for t in report["traces"]) else "fit")
    for e in report["effects"]:
        if e["accepted"]:
            print(f"    {e['name']} {_judged_on(e.get('judged_on'))} RMSE per channel: {verdict_text(e['verdict'])}")
    for finding in ("model_form_mismatch", "unexplained_gap"):
        if report.get(finding):
            print(f"  {report[finding]['description']}")
    where = _where_line(report.get("where_summary") or {})
    if where:
        print(f"  {where}")
    v = report["final"]["verdict"]
    per_channel = verdict_text(v)
    print(f"  {on} RMSE nominal -> calibrated: {_improvement(v)} ({per_channel})" if report["accepted"]
          else f"  {on} RMSE nominal -> calibrated, per channel: {per_channel}")
    if report.get("calibrated_changes"):
        print(f"  calibrated.toml changes {', '.join(report['calibrated_changes'])} (report.json calibrated_diff)")
    hyb = report.get("hybrid")
    if hyb and hyb.get("model"):
        print(f"  learned residual model {hyb['model']} on top, {_judged_on(hyb.get('judged_on'))} RMSE: "
              f"{_improvement(hyb['verdict'])} "
              f"({verdict_text(hyb['verdict'])})")
    print(f"wrote {paths['json']}, {paths['html']}, {paths['toml']}")
    return 0


def _where_line(summary: dict) -> str:
    """Where the nominal model's gap concentrates, per channel its most concentrated bin (report.json
    ``where_summary``): the place to look when no effect, or an unexpected one, explains it."""
    parts = []
    for ch, bins in summary.items():
        if bins:
            b = bins[0]
            parts.append(f"{ch} {100 * b['share']:.0f} % in {b['dimension']} {b['bin']} ({b['concentration']:.1f}x "
                         "its share of the samples)")
    return ("the nominal model's gap concentrates: " + "; ".join(parts)) if parts else ""


def _judged_on(judged_on: str | None) -> str:
    """The data a figure was judged on, as the report says it (``"holdout"`` or ``"fit"``)."""
    return "held-out" if judged_on == "holdout" else "fit"


def _improvement(verdict: dict) -> str:
    """What a per-channel verdict says, in the terms it was decided in (each channel against its own noise)."""
    better, worse = verdict.get("better_channels", []), verdict.get("worse_channels", [])
    if worse:
        return f"worse beyond its noise in {', '.join(worse)}"
    if better:
        return f"better beyond its noise in {', '.join(better)}, no channel worse beyond it"
    return "no channel better or worse beyond its noise"
