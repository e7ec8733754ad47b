"""Trace writing and the ``simulate`` command's real-time factor: a baseline writer (``numpy.savetxt`` per
chunk) vs the compiled CSV formatter (in the simulating thread, and in a
writer thread of its own beside the next chunk's simulation, as ``simulate`` runs it now) vs NPZ, measured in
the same run.

    python benchmarks/bench_trace_writer.py [--reps 5] [--json out.json]

Two figures per variant:
- writer alone: wall time to write the columns of a seed-000 trace (21 s and 200 s at 1 kHz, 10 columns);
- the command: ``virtualaxis simulate --config configs/seed000-hust.toml --profile
  sine:stroke_mm=100,feed_mm_min=6000 --duration D --out t.<ext> --json s.json``, each repetition a fresh process,
  reporting the command's own ``real_time_factor`` (simulated s / wall s of simulating + writing + closing the
  trace; start-up -- imports, config, the one-off numba kernel load -- is excluded and reported as ``startup_s``).
  The old-writer variant runs the same command with ``TraceWriter`` replaced by the old class; the
  one-thread variant with ``TraceWriter(threaded=False)`` (the compiled formatter in the simulating thread).
Medians of ``--reps`` repetitions, variants interleaved. The machine is shared and noisy.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "seed000-hust.toml"
PROFILE = "sine:stroke_mm=100,feed_mm_min=6000"

LEGACY = '''
import sys
from pathlib import Path
import numpy as np
import virtualaxis.sim.trace_io as tio

class OldTraceWriter:
    """The baseline writer (numpy.savetxt per chunk), verbatim apart from the name and the ignored
    threaded flag that simulate passes now."""
    def __init__(self, path, columns, *, threaded=False):
        self.path = Path(path)
        self.columns = ["t"] + [c for c in columns if c != "t"]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = self.path.open("w", newline="")
        self._fh.write(",".join(self.columns) + "\\n")
        self.rows = 0
    def write(self, data):
        block = np.column_stack([np.asarray(data[c], dtype=float) for c in self.columns])
        np.savetxt(self._fh, block, delimiter=",", fmt="%.10g")
        self.rows += len(block)
    def close(self):
        self._fh.close()
    def __enter__(self):
        return self
    def __exit__(self, *exc):
        self.close()

tio.TraceWriter = OldTraceWriter
from virtualaxis.cli.main import main
sys.exit(main(sys.argv[1:]))
'''

ONE_THREAD = '''
import sys
import virtualaxis.sim.trace_io as tio

class OneThreadWriter(tio.TraceWriter):
    """The compiled CSV formatter, run in the caller's thread (simulate before the writer thread)."""
    def __init__(self, path, columns, *, threaded=False):
        super().__init__(path, columns, threaded=False)

tio.TraceWriter = OneThreadWriter
from virtualaxis.cli.main import main
sys.exit(main(sys.argv[1:]))
'''

NEW = "import sys\nfrom virtualaxis.cli.main import main\nsys.exit(main(sys.argv[1:]))\n"


def run_command(code: str, duration_s: float, out: Path, js: Path) -> dict:
    args = [sys.executable, "-c", code, "simulate", "--config", str(CONFIG), "--profile", PROFILE,
            "--duration", str(duration_s), "--out", str(out), "--json", str(js), "--force"]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT / "src") + os.pathsep + env.get("PYTHONPATH", "")
    t0 = time.perf_counter()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
    total = time.perf_counter() - t0
    s = json.loads(js.read_text())
    return {"rtf": s["real_time_factor"], "wall_s": s["wall_s"], "startup_s": s.get("startup_s"),
            "process_s": total, "bytes": out.stat().st_size}


def writer_alone(n_rows: int, reps: int, tmp: Path) -> dict:
    sys.path.insert(0, str(ROOT / "src"))
    import virtualaxis.sim.trace_io as tio

    rng = np.random.default_rng(0)
    cols = ["pos_cmd", "pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q", "force_ext",
            "following_error"]
    data = {"t": np.arange(n_rows) * 1e-3}
    for c in cols:
        data[c] = rng.standard_normal(n_rows) * 1e-3
    tio.format_csv_rows(np.zeros((1, 2)))  # compiled-formatter cache load, as a command pays it once

    def old(path: Path) -> None:
        with path.open("w", newline="") as fh:
            fh.write(",".join(["t"] + cols) + "\n")
            for a in range(0, n_rows, 10000):
                blk = np.column_stack([data[c][a:a + 10000] for c in ["t"] + cols])
                np.savetxt(fh, blk, delimiter=",", fmt="%.10g")

    def new(path: Path) -> None:
        with tio.TraceWriter(path, cols) as w:
            for a in range(0, n_rows, 10000):
                w.write({c: v[a:a + 10000] for c, v in data.items()})

    res: dict[str, list[float]] = {"old_csv": [], "new_csv": [], "npz": []}
    for _ in range(reps):
        for name, fn, ext in (("old_csv", old, "csv"), ("new_csv", new, "csv"), ("npz", new, "npz")):
            p = tmp / f"w.{ext}"
            t0 = time.perf_counter()
            fn(p)
            res[name].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in res.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    out: dict = {"machine": f"{platform.processor() or platform.machine()}, nproc {os.cpu_count()}",
                 "python": platform.python_version(), "load_average": os.getloadavg()}
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        for n_rows in (21001, 200001):
            w = writer_alone(n_rows, a.reps, tmp)
            out[f"writer_alone_{n_rows}_rows_s"] = w
            print(f"writer alone, {n_rows} rows x 10 columns: old savetxt {w['old_csv'] * 1e3:.1f} ms, "
                  f"new CSV {w['new_csv'] * 1e3:.1f} ms ({w['old_csv'] / w['new_csv']:.1f}x), "
                  f"NPZ {w['npz'] * 1e3:.1f} ms ({w['old_csv'] / w['npz']:.1f}x)", flush=True)
        for dur in (21.0, 200.0):
            runs: dict[str, list[dict]] = {"old_csv": [], "csv_one_thread": [], "new_csv": [], "npz": []}
            for _ in range(a.reps):
                for name, code, ext in (("old_csv", LEGACY, "csv"), ("csv_one_thread", ONE_THREAD, "csv"),
                                        ("new_csv", NEW, "csv"), ("npz", NEW, "npz")):
                    runs[name].append(run_command(code, dur, tmp / f"t.{ext}", tmp / "s.json"))
            summary = {}
            for name, rs in runs.items():
                summary[name] = {k: statistics.median(r[k] for r in rs) for k in rs[0] if rs[0][k] is not None}
                summary[name]["rtf_min"] = min(r["rtf"] for r in rs)
                summary[name]["rtf_max"] = max(r["rtf"] for r in rs)
            out[f"simulate_{dur:g}s"] = summary
            print(f"simulate {dur:g} s: real_time_factor (median [min-max]) " + "; ".join(
                f"{k} {v['rtf']:.0f}x [{v['rtf_min']:.0f}-{v['rtf_max']:.0f}] wall {v['wall_s'] * 1e3:.0f} ms"
                f" startup {v.get('startup_s', float('nan')) * 1e3:.0f} ms, {v['bytes'] / 1e6:.1f} MB"
                for k, v in summary.items()), flush=True)
    out["load_average_end"] = os.getloadavg()
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
