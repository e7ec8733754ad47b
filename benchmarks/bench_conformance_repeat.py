"""The same verdicts every time on a busy machine: N consecutive full conformance runs against one drive
served in SYNC lockstep, with CPU-bound processes beside it (``python -c "while True: pass"``, 4 by default).

    python benchmarks/bench_conformance_repeat.py --runs 10 --hogs 4 --json out.json
    python benchmarks/bench_conformance_repeat.py --runs 30 --minutes 60   # as many of 30 as fit in an hour

Per run: the failed checks (with their reasons), the skips, the duration. At the end: runs with a failure,
and whether every run gave the same verdict for every check. Exit 1 on any failure or differing verdict.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_conformance_mutants import CLI, REPO, _spec, serve  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--hogs", type=int, default=4, help="CPU-bound processes beside the drive and the suite")
    ap.add_argument("--pacing", choices=("lockstep", "realtime"), default="lockstep")
    ap.add_argument("--minutes", type=float, default=None,
                    help="start no run after this many minutes (the runs done are reported)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None, help="directory for the full report of each run with a failure")
    args = ap.parse_args()
    t_start = time.monotonic()
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hogs)]
    spec = _spec()
    proc = serve(None, spec, args.pacing == "lockstep")
    runs = []
    try:
        for k in range(args.runs):
            if args.minutes is not None and time.monotonic() - t_start > 60 * args.minutes:
                print(f"--minutes {args.minutes:g} reached after {k} run(s)", flush=True)
                break
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / "r.json"
                t0 = time.monotonic()
                r = subprocess.run([*CLI, "conformance", "--can", spec, "--pacing", args.pacing, "--json", str(out)],
                                   capture_output=True, text=True, cwd=REPO, timeout=1800,
                                   env={**os.environ, "PYTHONUNBUFFERED": "1"})
                dt = time.monotonic() - t0
                load = round(os.getloadavg()[0], 1)
                if not out.exists():
                    print(f"run {k + 1}: no report (exit {r.returncode}): {r.stdout[-800:]}{r.stderr[-800:]}")
                    runs.append({"verdicts": {}, "failed": [["(run)", "no report"]], "seconds": round(dt, 1),
                                 "load_1min": load})
                    continue
                rep = json.loads(out.read_text())
            verdicts = {c["id"]: c["status"] for c in rep["checks"]}
            failed = [[c["id"], c["detail"]] for c in rep["checks"] if c["status"] == "fail"]
            skipped = sorted(i for i, s in verdicts.items() if s == "skipped")
            runs.append({"verdicts": verdicts, "failed": failed, "skipped": skipped, "seconds": round(dt, 1),
                         "sdo_retries": rep["summary"].get("sdo_retries", 0), "load_1min": load})
            print(f"run {k + 1}/{args.runs}: {len(verdicts)} checks, {len(failed)} failed "
                  f"{[f[0] for f in failed]}, skipped {skipped}, {rep['summary'].get('sdo_retries', 0)} SDO "
                  f"retries, {dt:.1f} s, load average {load}", flush=True)
            for cid, detail in failed:
                print(f"  {cid}: {detail}", flush=True)
            if failed and args.keep:
                keep = Path(args.keep)
                keep.mkdir(parents=True, exist_ok=True)
                (keep / f"run{k + 1}.json").write_text(json.dumps(rep, indent=1))
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
        for h in hogs:
            h.kill()
            h.wait()
    with_failure = sum(bool(r["failed"]) for r in runs)
    first = runs[0]["verdicts"] if runs else {}
    identical = all(r["verdicts"] == first for r in runs)
    secs = [r["seconds"] for r in runs] or [0.0]
    loads = [r["load_1min"] for r in runs] or [0.0]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=REPO).stdout.strip() or "unknown"
    print(f"summary: {len(runs)} runs with {args.hogs} CPU hogs ({os.cpu_count()} CPUs), {with_failure} with a "
          f"failure, verdicts {'identical' if identical else 'DIFFER'}; run time {min(secs):.1f}..{max(secs):.1f} s; "
          f"1-min load average at the runs' ends {min(loads):.1f}..{max(loads):.1f}; code {commit}")
    if args.json:
        Path(args.json).write_text(json.dumps({"runs": runs, "hogs": args.hogs, "with_failure": with_failure,
                                               "identical": identical, "commit": commit,
                                               "load_1min": [min(loads), max(loads)]}, indent=1))
    return 0 if not with_failure and identical else 1


if __name__ == "__main__":
    sys.exit(main())
