"""Does the live page disturb the drive? SYNC -> TPDO latency and late cycles of a CSP move on 3 axes at 1 ms
SYNC, with and without the page open in 10 browser tabs, in the same run.

Each phase starts its own ``virtualaxis serve`` process with three axes (nodes 1..3, real-time pacing, 1 ms
drive cycle, ``--bitrate 0``) on a host-local ``udp_multicast`` bus; this process is the CANopen master
(``_master.py``: SYNC + a synchronous CSP target RPDO per axis every 1 ms, a 20 mm sine at 0.5 Hz, TPDO2 answered
on every SYNC).

- ``off``: ``serve`` without ``--http``;
- ``page``: ``serve --http`` and headless Chromium with **10 tabs** of the page (axes 1, 2, 3, 1, 2, ...), each in
  a window of its own and none throttled as a background tab, each drawing its scope at the browser's frame rate
  (at most 60 fps; the frames each tab drew per second are reported), fed by the page's WebSocket (every drive
  cycle's samples, ~60 messages/s per tab).

Phases alternate ``--rounds`` times so that drifting machine load hits both alike. Reported per phase: the SYNC
-> TPDO latency percentiles over the three axes (kernel receive timestamps, as ``bench_side_channels.py``),
missed and late TPDOs, the drive cycles the pacing started late in the window (OD 0x2110:2 of node 1), and the
CPU time of serve. The shift is ``page - off`` of the medians over the rounds.

    python benchmarks/bench_live_page.py --seconds 10 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _master import (  # noqa: E402
    CLI,
    REPO,
    SYNC_COB,
    SdoReply,
    TpdoClock,
    cpu_seconds,
    free_port,
    latency_stats,
    machine_info,
    sdo,
    setup_csp,
    sync_loop,
)

PERIOD_S = 0.001
NODES = (1, 2, 3)
TABS = 10
CONFIG = "configs/seed000-hust.toml"


def _late_cycles(bus, reply) -> int | None:
    """Node 1's late drive cycles (OD 0x2110:2); None if the SDO got no answer within 10 s (a starved serve)."""
    try:
        return sdo(bus, reply, 1, 0x2110, 2, timeout_s=10.0)
    except RuntimeError:
        return None


def run_phase(phase: str, seconds: float, port: int, tmp: Path) -> dict:
    group = "239.74.163.9"
    spec = f"udp_multicast:{group},port={port}"
    http_port = free_port()
    args = [*CLI, "serve", "--can", spec, "--status-interval", "0", "--duration", str(seconds + 120),
            "--bitrate", "0", *[f"--axis={'XYZ'[i]}={n}:{CONFIG}" for i, n in enumerate(NODES)]]
    if phase == "page":
        args += ["--http", f"127.0.0.1:{http_port}"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise RuntimeError(f"serve did not start: {line} {proc.stderr.read()}")
    if phase == "page":
        proc.stdout.readline()  # "http: ..."
    bus = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
    clock = TpdoClock([*(0x280 + n for n in NODES), SYNC_COB])
    reply = SdoReply(list(NODES))
    notifier = can.Notifier(bus, [clock, reply], timeout=0.05)
    browser = None
    out: dict = {"phase": phase, "seconds": seconds}
    try:
        targets = {n: setup_csp(bus, reply, n) for n in NODES}
        if phase == "page":
            from cdp_browser import Browser

            # each tab in a window of its own, none throttled as a background tab: all ten draw (as ten visible
            # windows on a control-room screen would)
            browser = Browser.launch(extra_args=("--disable-background-timer-throttling",
                                                 "--disable-renderer-backgrounding",
                                                 "--disable-backgrounding-occluded-windows"))
            tabs = [browser.open(f"http://127.0.0.1:{http_port}/?axis={'XYZ'[i % 3]}", new_window=True)
                    for i in range(TABS)]
            for t in tabs:
                t.wait_for("window.livePage && window.livePage.samplesReceived > 0", timeout_s=60)
            for t in tabs:  # count the frames each tab draws
                t.evaluate("window.__frames = 0; (function f() { window.__frames++; requestAnimationFrame(f); })()")
            time.sleep(1.0)
        overruns0 = _late_cycles(bus, reply)
        cpu0, t0 = cpu_seconds(proc.pid), time.perf_counter()
        if browser is not None:
            frames0 = [t.evaluate("[window.__frames, window.livePage.samplesReceived, window.livePage.gaps]")
                       for t in tabs]
        clock.clear()
        n_sync = int(seconds / PERIOD_S)
        user_sync = sync_loop(bus, dict(targets), PERIOD_S, n_sync, spin_s=3e-4)
        time.sleep(0.2)
        wall = time.perf_counter() - t0
        overruns1 = _late_cycles(bus, reply)
        out["window_overruns"] = None if None in (overruns0, overruns1) else overruns1 - overruns0
        out["serve_cpu_percent"] = 100.0 * (cpu_seconds(proc.pid) - cpu0) / wall
        if browser is not None:
            frames1 = [t.evaluate("[window.__frames, window.livePage.samplesReceived, window.livePage.gaps]")
                       for t in tabs]
            out["tab_fps"] = [round((b[0] - a[0]) / wall, 1) for a, b in zip(frames0, frames1, strict=True)]
            out["tab_samples_per_s"] = [round((b[1] - a[1]) / wall) for a, b in zip(frames0, frames1, strict=True)]
            out["tab_gaps"] = [b[2] for b in frames1]
        wire_sync = np.array(clock.times[SYNC_COB])
        if len(wire_sync) != n_sync:
            out["wire_sync_missing"] = int(n_sync - len(wire_sync))
            wire_sync = user_sync
        out["syncs"] = n_sync
        per_node = {n: latency_stats(np.array(clock.times[0x280 + n]), wire_sync, PERIOD_S) for n in NODES}
        out["per_node"] = per_node
        for key in ("latency_us_p50", "latency_us_p99", "latency_us_max"):
            if all(v.get(key) is not None for v in per_node.values()):
                out[key] = max(v[key] for v in per_node.values())
        out["missed"] = sum(v["missed_cycles"] for v in per_node.values())
        out["late"] = sum(v["late_tpdos"] for v in per_node.values())
    finally:
        if browser is not None:
            browser.close()
        notifier.stop()
        bus.shutdown()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    return out


def hook_cost(cycles: int = 4000, repeats: int = 7) -> dict:
    """In-process cost of the page's cycle hook: one drive in CSP (a target written and one ``Drive.step`` per
    cycle), alternately without and with the sample ring attached; best of ``repeats`` runs of ``cycles`` cycles
    [us of this thread's CPU time per cycle]; and the page thread's cost of draining (converting) one second of
    cycles."""
    from virtualaxis.config import load_axis_config
    from virtualaxis.drive.core import Drive
    from virtualaxis.services.http.ring import SampleRing

    drive = Drive(load_axis_config(REPO / CONFIG))
    drive.write_object(0x6060, 0, 8)
    for cw in (6, 7, 15):
        drive.write_object(0x6040, 0, cw)
    ring = SampleRing(drive, 60.0)
    k = [0]

    def run(drain_every: int = 0) -> tuple[float, float]:
        """(drive cycle, drain) CPU time per cycle [us]; a drain every ``drain_every`` cycles (as the page's
        thread does at 60 Hz and 1 kHz: every ~16 cycles), timed apart."""
        spent = 0.0
        t0 = time.thread_time()
        for i in range(cycles):
            k[0] += 1
            drive.write_object(0x607A, 0, int(10000 * np.sin(k[0] * 2e-3)))
            drive.step(1)
            if drain_every and i % drain_every == drain_every - 1:
                t1 = time.thread_time()
                ring.drain()
                spent += time.thread_time() - t1
        total = time.thread_time() - t0
        return (total - spent) / cycles * 1e6, spent / cycles * 1e6

    run()
    best = {"without": float("inf"), "with": float("inf")}
    drain = float("inf")
    for _ in range(repeats):
        best["without"] = min(best["without"], run()[0])
        ring.attach()
        with_page, drain_us = run(16)
        best["with"] = min(best["with"], with_page)
        drain = min(drain, drain_us)
        ring.detach()
    return {"cycle_us_without_page": best["without"], "cycle_us_with_page": best["with"],
            "hook_us": best["with"] - best["without"], "ratio": best["with"] / best["without"],
            "drain_us_per_cycle": drain}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="per phase")
    ap.add_argument("--rounds", type=int, default=2, help="passes over off, page")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--hook-cost", action="store_true", help="only the in-process cost of the page's cycle hook")
    opts = ap.parse_args()
    if opts.hook_cost:
        res = hook_cost()
        print(json.dumps(res | {"machine": machine_info()}, indent=1))
        return 0
    import tempfile

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(opts.rounds):
            for phase in ("off", "page"):
                res = run_phase(phase, opts.seconds, free_port(), Path(tmp))
                res["round"] = r
                results.append(res)
                print(json.dumps({k: v for k, v in res.items() if k != "per_node"}), flush=True)

    def med(phase: str, key: str) -> float:
        vals = [r[key] for r in results if r["phase"] == phase and r.get(key) is not None]
        return float(np.median(vals)) if vals else float("nan")

    summary = {"machine": machine_info(), "rounds": results}
    print(f"\n{'':24s}{'off':>10s}{'page':>10s}{'shift':>10s}")
    for key in ("latency_us_p50", "latency_us_p99", "latency_us_max", "window_overruns", "missed", "late",
                "serve_cpu_percent"):
        a, b = med("off", key), med("page", key)
        summary[key] = {"off": a, "page": b, "shift": b - a}
        print(f"{key:24s}{a:10.1f}{b:10.1f}{b - a:+10.1f}")
    fps = [f for r in results if r["phase"] == "page" for f in r.get("tab_fps", [])]
    if fps:
        print(f"tabs: {TABS}, frames/s per tab median {np.median(fps):.0f} (min {min(fps):.0f}), "
              f"gaps in the streams {sum(sum(r.get('tab_gaps', [])) for r in results)}")
    if opts.json:
        Path(opts.json).write_text(json.dumps(summary, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
