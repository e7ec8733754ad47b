"""Does the conformance suite catch broken drives, and only broken ones?

Serves our drive with each planted defect of ``virtualaxis.conformance.mutants`` (one behaviour broken per
mutant, `python -m virtualaxis.conformance.mutants NAME serve ...`) in its own process on a private
udp_multicast group, runs `virtualaxis conformance` against it (the mutant's pacing; its checks, or the whole
suite with ``--full``) and reports per mutant: killed or survived, and the checks that failed. The unmodified
drive is served once per pacing with every check some mutant runs: any failure there is a false alarm of the
suite. ``--jobs N`` serves and runs N at a time (each on its own group).

    python benchmarks/bench_conformance_mutants.py                 # every mutant, its checks
    python benchmarks/bench_conformance_mutants.py --full          # every mutant, the whole suite
    python benchmarks/bench_conformance_mutants.py --mutants heartbeat_slow,csp_target_late --json out.json
    python benchmarks/bench_conformance_mutants.py --jobs 3 --json out.json       # three at a time
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
CLI = [PY, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


def _spec() -> str:
    rng = random.Random(os.getpid() * 7919 + time.perf_counter_ns())
    return f"udp_multicast:239.74.{rng.randint(100, 250)}.{rng.randint(1, 250)},port={rng.randint(46000, 49000)}"


def serve(mutant: str | None, spec: str, lockstep: bool) -> subprocess.Popen:
    args = ["serve", "--can", spec, "--status-interval", "0", "--allow-fault-injection"]
    if lockstep:
        args.append("--lockstep")
    cmd = [*CLI, *args] if mutant is None else [PY, "-m", "virtualaxis.conformance.mutants", mutant, *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    end = time.monotonic() + 600  # (a first start compiles the plant kernel: minutes on a loaded machine)
    while time.monotonic() < end:
        line = proc.stdout.readline()
        if not line or line.startswith("ready:"):
            break
    if proc.poll() is not None:
        raise RuntimeError(f"serve ({mutant or 'unmodified'}) did not start: {proc.stderr.read()[-2000:]}")
    return proc


def run_suite(spec: str, pacing: str, only: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "report.json"
        cmd = [*CLI, "conformance", "--can", spec, "--pacing", pacing, "--json", str(out)]
        if only:
            cmd += ["--only", only]
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=900)
        if not out.exists():
            raise RuntimeError(f"conformance wrote no report (exit {r.returncode}): "
                               f"{r.stdout[-1500:]}{r.stderr[-1500:]}")
        return json.loads(out.read_text())


def _behaviour(name: str) -> str:
    from virtualaxis.conformance.mutants import MUTANTS

    return MUTANTS[name].behaviour


def one(mutant: str | None, pacing: str, only: str) -> dict:
    spec = _spec()
    proc = serve(mutant, spec, pacing == "lockstep")
    t0 = time.monotonic()
    try:
        report = run_suite(spec, pacing, only)
    finally:
        proc.terminate()
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    failed = [(c["id"], c["detail"]) for c in report["checks"] if c["status"] == "fail"]
    return {"mutant": mutant or "(unmodified)", "pacing": pacing, "only": only or "all",
            "behaviour": "" if mutant is None else _behaviour(mutant),
            "checks": len(report["checks"]), "failed": failed, "killed": bool(failed),
            "seconds": round(time.monotonic() - t0, 1)}


def main() -> int:
    sys.path.insert(0, str(REPO / "src"))
    from virtualaxis.conformance.mutants import MUTANTS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mutants", default="", help="comma-separated mutant names (default: all)")
    ap.add_argument("--full", action="store_true", help="the whole suite against each mutant")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--jobs", type=int, default=1, help="mutants served and run at the same time")
    args = ap.parse_args()
    names = [n.strip() for n in args.mutants.split(",") if n.strip()] or list(MUTANTS)
    unknown = [n for n in names if n not in MUTANTS]
    if unknown:
        print(f"error: --mutants: unknown {', '.join(unknown)} (known: {', '.join(MUTANTS)})", file=sys.stderr)
        return 2
    # the unmodified drive once per pacing, with every check some mutant runs (the whole suite if one runs it)
    selections: dict[str, list[str]] = {}
    for name in names:
        m = MUTANTS[name]
        selections.setdefault(m.pacing, []).append("" if args.full else m.only)
    tasks: list[tuple[str | None, str, str]] = []
    for pacing, onlys in selections.items():
        tasks.append((None, pacing, "" if "" in onlys else ",".join(dict.fromkeys(",".join(onlys).split(",")))))
    for name in names:
        m = MUTANTS[name]
        tasks.append((name, m.pacing, "" if args.full else m.only))

    def run(task: tuple[str | None, str, str]) -> dict:
        res = one(*task)
        if task[0] is None:
            verdict = ("FALSE ALARM " + ", ".join(i for i, _ in res["failed"])) if res["failed"] else "all pass"
        else:
            verdict = "KILLED by " + ", ".join(i for i, _ in res["failed"]) if res["killed"] else "SURVIVED"
        print(f"{res['mutant']:<40} {task[1]:<9} {res['checks']:>3} checks: {verdict}  ({res['seconds']} s)",
              flush=True)
        return res

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        rows = list(pool.map(run, tasks))
    baselines = selections
    mutants = [r for r in rows if r["mutant"] != "(unmodified)"]
    killed = sum(r["killed"] for r in mutants)
    false_alarms = sum(bool(r["failed"]) for r in rows if r["mutant"] == "(unmodified)")
    print(f"summary: {killed} of {len(mutants)} mutants killed; {false_alarms} false alarm(s) on the unmodified drive "
          f"in {len(baselines)} run(s)")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=REPO).stdout.strip() or "unknown"
    print(f"code {commit}; 1-min load average at the end {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "killed": killed, "mutants": len(mutants),
                                               "false_alarms": false_alarms, "commit": commit}, indent=1))
    return 0 if killed == len(mutants) and not false_alarms else 1


if __name__ == "__main__":
    sys.exit(main())
