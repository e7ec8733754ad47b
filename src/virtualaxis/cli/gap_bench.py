"""``virtualaxis gap-bench``: withheld-effect cases with a known answer, diagnosed and scored."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "gap-bench",
        help="generate withheld-effect cases, diagnose them and score the diagnosis",
        description="For each effect of the library (and pairs, and clean cases) simulate 'measured' traces "
        "with the effect and diagnose them against the nominal config without it.",
    )
    p.add_argument("--out", metavar="DIR", help="output directory (required unless --list); a new or empty folder "
                   "unless --force")
    p.add_argument("--force", action="store_true", help="write into a folder that already holds files (results "
                   "of the same cases are replaced)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cases", default=None, help="comma-separated case names (default: all, or the quick set)")
    p.add_argument("--quick", action="store_true", help="short traces (10 mm stroke) and a handful of cases")
    p.add_argument("--jobs", type=int, default=None, help="worker processes (default 2; at most 2 per CPU and what "
                   "the available memory holds)")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--suite", choices=("reference", "own", "both"), default="reference",
                   help="reference: cases made by the independent reference axis (virtualaxis.refaxis, the "
                   "acceptance figures); own: cases made by our own simulator (second column); both")
    p.add_argument("--door", choices=("cli", "library"), default="cli",
                   help="cli (default): diagnose each case by running 'virtualaxis diagnose' on its files in a "
                   "subprocess, as a user does; library: call the diagnosis in this process")
    p.set_defaults(func=run)


def _pct(x) -> str:  # "-" where the run had no case of that kind (NaN)
    return "-" if x is None or x != x else f"{100 * x:.0f} %"


def _case_list(text: str | None, known: list[str], what: str) -> list[str] | None:
    """``--cases`` checked before any bar or run starts: not empty, no empty item, no unknown or repeated name."""
    from virtualaxis.cli.errors import CliError

    if text is None:
        return None
    names = [n.strip() for n in text.split(",")]
    if not text.strip() or "" in names:
        raise CliError(f"--cases: empty case name in {text!r}; give comma-separated names (see --list) or leave "
                       "the option out for all")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise CliError(f"--cases: unknown {what}(s) {', '.join(unknown)} (virtualaxis gap-bench --list shows the "
                       f"{len(known)} names)")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise CliError(f"--cases: {', '.join(dup)} given twice")
    return names


def run_reference(args: argparse.Namespace, out_dir: Path) -> dict:
    """The independent reference axis' cases (virtualaxis.gapbench)."""
    from tqdm import tqdm

    from virtualaxis.gapbench.reference import run_reference_bench
    from virtualaxis.refaxis import case_names

    names = _case_list(args.cases, list(case_names()), "reference case") or list(case_names())
    bar = tqdm(total=len(names), desc="gap bench (reference axis)", unit="case", disable=None)

    def progress(ev: dict) -> None:
        bar.update(1)
        if ev.get("failed"):
            bar.write(f"{ev['case']:40s} FAILED: virtualaxis diagnose exit {ev['exit_code']}: {ev['error']}")
            return
        bar.write(f"{ev['case']:40s} truth={'+'.join(ev['truth']) or '-':32s} "
                  f"found={'+'.join(ev['answer']) or ev['conclusion']}")

    try:
        out = run_reference_bench(out_dir, seed=args.seed, case_names=names, quick=args.quick, jobs=args.jobs,
                                  progress=progress, door=args.door)
    finally:
        bar.close()
    s = out["summary"]
    print(f"reference axis: right effect first {_pct(s['right_effect_first'])}, clean cases with nothing accepted "
          f"{_pct(s['clean_nothing_accepted'])}, no accepted effect outside the truth {_pct(s['none_outside_truth'])}, "
          f"main parameter within 15 % {_pct(s['param_within_15pct'])}, held-out shrink >= 60 % on the effect's "
          f"channel {_pct(s['shrink_ge_60pct'])}")
    if out.get("failed"):
        print(f"{len(out['failed'])} case(s) not scored: virtualaxis diagnose failed on "
              f"{', '.join(f['case'] for f in out['failed'])}")
    print(f"wrote {out_dir / 'reference.json'}")
    return out


def run(args: argparse.Namespace) -> int:
    from virtualaxis.cli.common import check_jobs
    from virtualaxis.cli.errors import CliError

    if args.seed < 0:
        raise CliError(f"--seed must be >= 0 (got --seed {args.seed})")
    args.jobs = check_jobs(args.jobs)
    from tqdm import tqdm

    from virtualaxis.diagnosis.bench import QUICK_CASES, all_cases, run_bench

    if args.list and args.suite != "own":
        from virtualaxis.refaxis import case_names

        for n in case_names():
            print(f"reference  {n}")
        if args.suite == "reference":
            return 0
    if args.list:
        for c in all_cases():
            print(f"{c.name:22s} {c.axis:10s} {'+'.join(c.effects) or '(clean)'}")
        return 0
    if not args.out:
        from virtualaxis.cli.main import CliError

        raise CliError("gap-bench needs --out DIR")
    _check_out_dir(Path(args.out), args.force)
    if args.suite in ("reference", "both"):
        run_reference(args, Path(args.out) / "reference" if args.suite == "both" else Path(args.out))
        if args.suite == "reference":
            return 0
        args.cases = None  # the reference's case names are not our own cases
    names = _case_list(args.cases, [c.name for c in all_cases()], "case")
    total = len(names) if names else (len(QUICK_CASES) if args.quick else len(all_cases()))
    bar = tqdm(total=total, desc="gap bench", unit="case", disable=None)

    def progress(ev: dict) -> None:
        bar.update(1)
        bar.write(f"{ev['case']:22s} truth={'+'.join(ev['truth']) or '-':32s} "
                  f"found={'+'.join(ev['accepted']) or 'no significant effect'}")

    own_dir = Path(args.out) / "own" if args.suite == "both" else Path(args.out)
    try:
        out = run_bench(own_dir, seed=args.seed, case_names=names, quick=args.quick, jobs=args.jobs,
                        progress=progress, door=args.door)
    finally:
        bar.close()
    s = out["summary"]
    pct = _pct
    print(f"our own simulator: top-1 {pct(s['top1_accuracy'])}, top-2 {pct(s['top2_accuracy'])}, "
          f"false positives on clean cases {pct(s['false_positive_rate'])}, "
          f"parameters within 15 %: {pct(s['param_within_15pct'])}")
    print(f"wrote {own_dir / 'bench.json'}")
    return 0


def _check_out_dir(out: Path, force: bool) -> None:
    """A bench writes many files (traces, per-case reports, bench.json): into a new or empty folder, or with
    ``--force``; never into a file or a virtual file system."""
    from virtualaxis.cli.main import CliError
    from virtualaxis.cli.outputs import check_output_dir

    if out.is_dir() and any(out.iterdir()) and not force:
        raise CliError(f"--out {out}: folder exists and holds files (use --force to write into it)")
    check_output_dir(out, True, [], "--out")
