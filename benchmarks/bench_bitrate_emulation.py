"""CPU cost of the CAN bit-rate emulation (``serve --bitrate``, :class:`virtualaxis.runtime.bitrate.BitRateBus`).

A sender thread hands ``--frames`` 8-byte frames (random data, as a moving axis' TPDOs; one identifier per
frame, as one TPDO per axis) to the bus once per millisecond, as the runtime thread answers a 1 ms SYNC, for
``--seconds``. Measured per frame: the CPU time of the sending thread in ``send`` (the runtime thread's share:
it delays the drive's next answer), the CPU time of the emulation's own threads, and the process' CPU in
percent of one core. The baseline, measured in the same run: the same loop on the bare python-can ``virtual``
bus (no emulation). Every frame must reach the wire (``frames_sent``); the largest queueing delay is shown.

    python benchmarks/bench_bitrate_emulation.py
    python benchmarks/bench_bitrate_emulation.py --code old=/path/to/old-checkout --code new=. --rounds 3

``--code NAME=DIR`` (repeated): the emulation of each checkout (``DIR/src``), runs interleaved within each of
``--rounds`` rounds; per version the median over the rounds. State the host's ``bench_drive_latency.py
--cycle-cost`` beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, os, sys, threading, time
sys.path.insert(0, SRC)
import can
emulated = MODE == "emulated"
inner = can.Bus(interface="virtual", channel=f"bench-bitrate-{os.getpid()}")
if emulated:
    from virtualaxis.runtime.bitrate import BitRateBus
    bus = BitRateBus(inner, 1_000_000)
else:
    bus = inner
rng = __import__("random").Random(1)
n_cycles = int(SECONDS * 1000)
frames = [[can.Message(arbitration_id=0x281 + a, data=bytes(rng.getrandbits(8) for _ in range(8)),
                       is_extended_id=False) for a in range(FRAMES)] for _ in range(n_cycles)]
own_threads = [t for t in threading.enumerate() if t.name.startswith("can-bitrate")]
clocks = [time.pthread_getcpuclockid(t.ident) for t in own_threads]
threads0 = [time.clock_gettime(c) for c in clocks]
r0 = os.times()
send_cpu = 0.0
t0 = time.perf_counter()
for k in range(n_cycles):
    s = time.thread_time()
    for m in frames[k]:
        bus.send(m)
    send_cpu += time.thread_time() - s
    while time.perf_counter() - t0 < (k + 1) * 1e-3:
        time.sleep(0.0002)
time.sleep(0.05)
elapsed = time.perf_counter() - t0
r1 = os.times()
threads_cpu = sum(time.clock_gettime(c) - c0 for c, c0 in zip(clocks, threads0))
n = n_cycles * FRAMES
out = {"send_us_per_frame": 1e6 * send_cpu / n, "emulation_threads_us_per_frame": 1e6 * threads_cpu / n,
       "process_cpu_percent": 100.0 * ((r1.user - r0.user) + (r1.system - r0.system)) / elapsed}
if emulated:
    st = bus.stats()
    out.update(frames_sent=st["frames_sent"], frames=n, tx_delay_max_ms=st["tx_delay_max_ms"])
bus.shutdown()
print(json.dumps(out))
"""


def run(src: str, mode: str, frames: int, seconds: float) -> dict:
    code = (f"SRC = {src!r}\nMODE = {mode!r}\nFRAMES = {frames}\nSECONDS = {seconds}\n") + _CHILD
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    if res.returncode != 0:
        raise RuntimeError(f"{src} {mode}: {res.stderr.strip().splitlines()[-1:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--code", action="append", default=[], help="NAME=DIR, a checkout (repeat); default: this one")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=3, help="frames per 1 ms cycle (one TPDO per axis)")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--json", default=None, help="results file (written only when given)")
    args = ap.parse_args()
    codes = [("this", str(REPO / "src"))]
    if args.code:
        codes = []
        for item in args.code:
            name, _, root = item.partition("=")
            src = Path(root).resolve() / "src"
            if not name or not (src / "virtualaxis" / "runtime" / "bitrate.py").is_file():
                raise SystemExit(f"--code {item}: expected NAME=DIR with DIR a checkout with the bit-rate emulation")
            codes.append((name, str(src)))
    rows: dict[str, list[dict]] = {}
    try:
        from tqdm import tqdm
    except ImportError:  # (plain loop without the progress bar)
        def tqdm(x, **_k):
            return x
    plan = [(r, name, src, mode) for r in range(args.rounds) for name, src in codes
            for mode in (("bare", "emulated") if name == codes[0][0] else ("emulated",))]
    for _r, name, src, mode in tqdm(plan, desc="runs", unit="run", disable=not sys.stderr.isatty()):
        key = "bare virtual bus" if mode == "bare" else name
        rows.setdefault(key, []).append(run(src, mode, args.frames, args.seconds))
    print(f"{args.frames} frames per 1 ms, {args.seconds:g} s per run, {args.rounds} rounds (medians); "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    print(f"{'version':<18} {'send us/frame':>14} {'emulation us/frame':>19} {'process CPU':>12} {'sent':>12} "
          f"{'max delay ms':>13}")
    base = None
    summary = {}
    for key, got in rows.items():
        med = {k: statistics.median(g[k] for g in got) for k in got[0] if k not in ("frames",)}
        summary[key] = med
        if base is None:
            base = med
        sent = f"{med['frames_sent']:.0f}/{got[0]['frames']}" if "frames_sent" in med else "-"
        delay = f"{med['tx_delay_max_ms']:.2f}" if "tx_delay_max_ms" in med else "-"
        print(f"{key:<18} {med['send_us_per_frame']:>14.1f} {med['emulation_threads_us_per_frame']:>19.1f} "
              f"{med['process_cpu_percent']:>11.1f}% {sent:>12} {delay:>13}")
    for key, med in summary.items():
        if key != "bare virtual bus":
            print(f"{key}: send {med['send_us_per_frame'] / base['send_us_per_frame']:.2f}x the bare bus's, "
                  f"process CPU +{med['process_cpu_percent'] - base['process_cpu_percent']:.1f} % of a core")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "summary": summary, "runs": rows}, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
