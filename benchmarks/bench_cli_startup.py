"""Start-up cost of the ``virtualaxis`` command: CPU time (user + sys) and wall time of ``virtualaxis --help``
and of ``virtualaxis COMMAND --help`` for each command, each a fresh interpreter, against a baseline measured
in the same run: an interpreter that imports numpy only.

    python benchmarks/bench_cli_startup.py [--repeat 5] [--tree PATH/src]

``--tree`` runs the commands of another source tree (its ``src`` folder on PYTHONPATH), e.g. an export of an
earlier commit, for a comparison on the same host and load. Prints medians; CPU time is the steadier figure on
a shared host (wall time grows with the load, CPU time much less).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
COMMANDS = ("simulate", "serve", "diagnose", "rcsa", "identify-joints", "fault", "conformance")


def _run(code: str, src: Path) -> tuple[float, float]:
    """Wall and CPU seconds (user + sys of the child) of ``python -c code`` with ``src`` on PYTHONPATH."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(src)},
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--tree", type=Path, default=SRC, help="the src folder whose virtualaxis is run")
    args = ap.parse_args()
    cases = {"baseline: import numpy": "import numpy"}
    cli = "import sys; from virtualaxis.cli.main import main; sys.exit(main({argv!r}))"
    cases["virtualaxis --help"] = cli.format(argv=["--help"])
    for name in COMMANDS:
        cases[f"virtualaxis {name} --help"] = cli.format(argv=[name, "--help"])
    samples: dict[str, list[tuple[float, float]]] = {k: [] for k in cases}
    for _ in range(args.repeat):  # interleaved: a change of load affects every case alike
        for name, code in cases.items():
            samples[name].append(_run(code, args.tree))
    base_cpu = statistics.median(c for _, c in samples["baseline: import numpy"])
    print(f"tree {args.tree}; load average {os.getloadavg()[0]:.1f}; medians of {args.repeat}")
    print(f"{'':34s} {'wall [s]':>9s} {'cpu [s]':>8s} {'cpu / baseline':>15s}")
    for name, rows in samples.items():
        wall = statistics.median(w for w, _ in rows)
        cpu = statistics.median(c for _, c in rows)
        print(f"{name:34s} {wall:9.2f} {cpu:8.2f} {cpu / base_cpu:15.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
