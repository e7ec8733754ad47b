"""How often an FMPy script that simulates the exported FMU ends with a crash, with and without the slave's guard.

    python benchmarks/bench_fmu_host_exit.py [--config configs/seed000-hust.toml] [--runs 20]

Each run is a process of its own, as a user's script: ``fmpy.simulate_fmu`` of the position-interface FMU for
0.1 s (FMPy instantiates, frees and unloads the FMU), standard output and error to files. The same number of runs,
interleaved, with the slave's exit guard switched off in the script (``binary_guards.release_state_at_exit``
replaced before the FMU is loaded) is the baseline measured in the same session. Prints the exit status counts and
the last line of standard error of each failed run.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIMULATE = "r = fmpy.simulate_fmu(sys.argv[1], stop_time=0.1, step_size=0.001); print(len(r), r['pos_fb'][-1])"
GUARDED = "import sys, fmpy; " + SIMULATE
UNGUARDED = ("import sys, fmpy; import virtualaxis.fmu.binary_guards as g; "
             "g.release_state_at_exit = lambda binary: False; " + SIMULATE)


def run_once(script: str, fmu: Path, folder: Path, tag: str) -> tuple[int, str]:
    out, err = folder / f"{tag}.out", folder / f"{tag}.err"
    with out.open("w") as fout, err.open("w") as ferr:
        rc = subprocess.run([sys.executable, "-c", script, str(fmu)], stdout=fout, stderr=ferr,
                            timeout=600).returncode
    lines = err.read_text(errors="replace").strip().splitlines()
    return rc, (lines[-1] if lines else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "seed000-hust.toml"))
    ap.add_argument("--runs", type=int, default=20)
    args = ap.parse_args()

    folder = Path(tempfile.mkdtemp(prefix="bench-fmu-exit-"))
    fmu = folder / "axis.fmu"
    subprocess.run([sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())",
                    "fmu", "--config", args.config, "--out", str(fmu)], check=True, capture_output=True)
    counts = {"guarded": collections.Counter(), "unguarded": collections.Counter()}
    t0 = time.monotonic()
    for i in range(args.runs):
        for name, script in (("guarded", GUARDED), ("unguarded", UNGUARDED)):
            rc, last = run_once(script, fmu, folder, f"{name}{i}")
            counts[name][rc] += 1
            if rc != 0:
                print(f"  run {i} {name}: exit status {rc}: {last}")
    print(f"{args.runs} runs each, {time.monotonic() - t0:.0f} s, {args.config}")
    for name, c in counts.items():
        bad = sum(n for rc, n in c.items() if rc != 0)
        print(f"{name:>9}: {args.runs - bad} of {args.runs} exited 0; exit statuses {dict(sorted(c.items()))}")


if __name__ == "__main__":
    main()
