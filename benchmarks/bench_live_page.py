"""Does the live page disturb the drive? SYNC -> TPDO latency and late cycles of a CSP move on 3 axes at 1 ms
SYNC, with and without the page's clients, in the same run.

Each phase starts its own ``virtualaxis serve`` process with three axes (nodes 1..3, real-time pacing, 1 ms
drive cycle, ``--bitrate 0``) on a host-local ``udp_multicast`` bus; this process is the CANopen master
(``_master.py``: SYNC + a synchronous CSP target RPDO per axis every 1 ms, a 20 mm sine at 0.5 Hz, TPDO2 answered
on every SYNC).

- ``off``: ``serve`` without ``--http``;
- ``streams``: ``serve --http`` and **10 WebSocket clients** in processes of their own, each reading
  ``/api/axes/NAME/live`` of one axis (X, Y, Z, X, ...) exactly as the page's script does (every message parsed
  as JSON, every scope message's samples decoded from base64 to float32, the sequence numbers checked for gaps);
  the clients run at nice 19 (``--sched-idle``: SCHED_IDLE) on the last CPU, so that they take as little CPU from
  the drive as a browser on another PC would: this phase measures the page's server in serve;
- ``browser``: ``serve --http`` and one headless Chromium with the page of axis X drawing at its frame rate
  (at most 60 fps), also at nice 19 (SCHED_IDLE) on the last CPU;
- ``page10`` (with ``--phases``): 10 Chromium windows at normal priority on any CPU -- on a 2-core host this
  measures the browsers' rendering beside the drive, not the server.

Phases alternate ``--rounds`` times so that drifting machine load hits all alike. Reported per phase: the SYNC
-> TPDO latency percentiles over the three axes (kernel receive timestamps, as ``bench_side_channels.py``),
missed and late TPDOs, the drive cycles the pacing started late in the window (OD 0x2110:2 of node 1), serve's
CPU share and threads (per OS thread name), the CPU share of serve's child processes (the page's server
process), the host's load average, and per client the messages and samples received per second and the gaps in
the sample sequence (a lost sample is a gap). The shift is ``phase - off`` of the medians over the rounds, with
the two-sided Mann-Whitney U p-value of the rounds (``_shifts``); the host's own tail is measured before and
after the rounds (``_master.host_jitter``: a plain-Python workload paced at 1 ms), and no shift smaller than
the scatter it causes can be seen.

``--rt-priority N``: serve and every thread of the master at SCHED_FIFO N (a host shared with other work).
``--pin DRIVE_CPUS:LOAD_CPUS`` (e.g. ``1:0``): serve's runtime and CAN receive threads on DRIVE_CPUS, everything
else of the run (serve's other threads, the page's server process, the clients, Chromium and the master, which
in a rig are other machines) on LOAD_CPUS: the isolated-core deployment of docs/side-channels.md, as
``bench_side_channels.py --pin``.
``--code NAME=SRC`` (repeated) runs every phase once per source tree (``PYTHONPATH=SRC`` for serve), interleaved
within each round: an A/B comparison of two versions of the package in the same run (phases ``off@NAME``, ...).

    python benchmarks/bench_live_page.py --seconds 10 --rounds 2
    python benchmarks/bench_live_page.py --seconds 5 --rounds 2 --code a=/tmp/a/src --code b=$PWD/src
    python benchmarks/bench_live_page.py --hook-cost      # the in-process cost of the page's cycle hook
"""

from __future__ import annotations

import argparse
import contextlib
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
    host_jitter,
    latency_stats,
    machine_info,
    schedstat_delta,
    sdo,
    set_priority,
    setup_csp,
    sync_loop,
    thread_schedstat,
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


DRIVE_THREADS = ("runtime", "can-rx")  # serve's threads on the SYNC -> TPDO path (OS names)


def make_idle(cpus: set[int] | None = None) -> None:
    """The calling process at nice 19 (with ``BENCH_SCHED_IDLE=1`` in the environment: SCHED_IDLE, which runs it
    only on CPU time nothing else wants) on ``cpus`` (default: ``BENCH_LOAD_CPUS`` of the environment, set by
    ``--pin``, else the last CPU)."""
    if cpus is None and os.environ.get("BENCH_LOAD_CPUS"):
        cpus = {int(c) for c in os.environ["BENCH_LOAD_CPUS"].split(",")}
    with contextlib.suppress(OSError):
        os.nice(19)
    if os.environ.get("BENCH_SCHED_IDLE") == "1":
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, cpus or {max(os.sched_getaffinity(0))})


def ws_client(url: str, out_path: str) -> int:
    """One client of the page's WebSocket, as the page's script reads it, until SIGTERM; writes
    ``{"recv": [[monotonic time, seq0, n], ...], "states": k, "gaps": g, "samples": s}`` to ``out_path``."""
    import base64

    from websockets.sync.client import connect

    make_idle()
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    recv: list[list] = []
    states = gaps = samples = 0
    last = -1
    with connect(url, max_size=16 * 1024 * 1024, open_timeout=30) as ws:
        announced = False
        while not stop[0]:
            try:
                text = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            m = json.loads(text)
            if m["event"] == "scope":
                d = m["data"]
                data = np.frombuffer(base64.b64decode(d["b64"]), dtype=np.float32)
                if data.size != d["n"] * d["cols"]:
                    raise RuntimeError(f"scope message of {data.size} values for {d['n']} x {d['cols']}")
                if last >= 0 and d["seq0"] != last + 1:
                    gaps += 1
                last = d["seq0"] + d["n"] - 1
                samples += d["n"]
                recv.append([time.monotonic(), d["seq0"], d["n"]])
                if not announced:
                    print("receiving", flush=True)
                    announced = True
            elif m["event"] == "state":
                states += 1
    Path(out_path).write_text(json.dumps({"recv": recv, "states": states, "gaps": gaps, "samples": samples}))
    return 0


def _window_rates(recv: list[list], t0: float, t1: float) -> tuple[float, float]:
    """(messages/s, samples/s) received in the monotonic window [t0, t1]."""
    inside = [r for r in recv if t0 <= r[0] <= t1]
    return len(inside) / (t1 - t0), sum(r[2] for r in inside) / (t1 - t0)


def _threads(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            return int(line.split()[1])
    return 0


def _children(pid: int) -> list[int]:
    out = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            out += [int(p) for p in Path(f"/proc/{pid}/task/{task}/children").read_text().split()]
    return out


def _cpu_of(pids: list[int]) -> float:
    total = 0.0
    for pid in pids:
        with contextlib.suppress(OSError):
            total += cpu_seconds(pid)
    return total


def pin_serve(pid: int, drive_cpus: set[int] | None, load_cpus: set[int] | None) -> None:
    """``--pin``: serve's SYNC path on ``drive_cpus``, its other threads and its child processes on ``load_cpus``."""
    if drive_cpus is None:
        return
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):
            name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
            os.sched_setaffinity(int(tid), drive_cpus if name in DRIVE_THREADS else load_cpus)
    for child in _children(pid):
        with contextlib.suppress(OSError):
            for tid in os.listdir(f"/proc/{child}/task"):
                os.sched_setaffinity(int(tid), load_cpus)


def run_phase(phase: str, seconds: float, port: int, tmp: Path, src: str | None = None, rt_priority: int = 0,
              drive_cpus: set[int] | None = None, load_cpus: set[int] | None = None) -> dict:
    group = "239.74.163.9"
    spec = f"udp_multicast:{group},port={port}"
    http_port = free_port()
    page = phase != "off"
    args = [*CLI, "serve", "--can", spec, "--status-interval", "0", "--duration", str(seconds + 120),
            "--bitrate", "0", *[f"--axis={'XYZ'[i]}={n}:{CONFIG}" for i, n in enumerate(NODES)]]
    if page:
        args += ["--http", f"127.0.0.1:{http_port}"]
    if rt_priority:
        args += ["--rt-priority", str(rt_priority)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"} | ({"PYTHONPATH": src} if src else {})
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise RuntimeError(f"serve did not start: {line} {proc.stderr.read()}")
    if page:
        proc.stdout.readline()  # "http: ..."
    pin_serve(proc.pid, drive_cpus, load_cpus)
    bus = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0)
    clock = TpdoClock([*(0x280 + n for n in NODES), SYNC_COB])
    reply = SdoReply(list(NODES))
    notifier = can.Notifier(bus, [clock, reply], timeout=0.05)
    browser = None
    clients: list[tuple[subprocess.Popen, Path]] = []
    tabs: list = []
    out: dict = {"phase": phase, "seconds": seconds, "loadavg_1min": os.getloadavg()[0]}
    try:
        targets = {n: setup_csp(bus, reply, n) for n in NODES}
        if phase == "streams":
            for i in range(TABS):
                path = tmp / f"client-{phase}-{i}.json"
                url = f"ws://127.0.0.1:{http_port}/api/axes/{'XYZ'[i % 3]}/live"
                c = subprocess.Popen([sys.executable, __file__, "--ws-client", url, "--json", str(path)],
                                     stdout=subprocess.PIPE, text=True, cwd=REPO)
                clients.append((c, path))
            for c, _ in clients:
                if c.stdout.readline().strip() != "receiving":
                    raise RuntimeError("a WebSocket client got no scope message")
        elif phase in ("browser", "page10"):
            from cdp_browser import Browser

            idle = phase == "browser"
            n_tabs = 1 if idle else TABS
            # none throttled as a background tab: each draws (as a visible window would)
            browser = Browser.launch(extra_args=("--disable-background-timer-throttling",
                                                 "--disable-renderer-backgrounding",
                                                 "--disable-backgrounding-occluded-windows"),
                                     preexec_fn=make_idle if idle else None)
            tabs = [browser.open(f"http://127.0.0.1:{http_port}/?axis={'XYZ'[i % 3]}", new_window=True)
                    for i in range(n_tabs)]
            for t in tabs:
                t.wait_for("window.livePage && window.livePage.samplesReceived > 0", timeout_s=120)
            for t in tabs:  # count the frames each tab draws
                t.evaluate("window.__frames = 0; (function f() { window.__frames++; requestAnimationFrame(f); })()")
        time.sleep(1.0)
        pin_serve(proc.pid, drive_cpus, load_cpus)  # (threads started since, e.g. per connection)
        overruns0 = _late_cycles(bus, reply)
        children = _children(proc.pid)
        cpu0, st0, child0 = cpu_seconds(proc.pid), thread_schedstat(proc.pid), _cpu_of(children)
        t0, m0 = time.perf_counter(), time.monotonic()
        probe = "[window.__frames, window.livePage.samplesReceived, window.livePage.gaps]"
        frames0 = [t.evaluate(probe) for t in tabs]
        clock.clear()
        n_sync = int(seconds / PERIOD_S)
        if rt_priority:  # (the master at the drive's priority for the window only: the clients keep theirs)
            # every thread of it: its receive thread, starved by the page's browser, would drop answers from its
            # socket buffer, counted as SYNCs the drive left unanswered
            set_priority(os.getpid(), rt_priority)
        try:
            # (under SCHED_FIFO the master sleeps to each SYNC: a spin would eat the real-time budget it shares
            # with serve, and the kernel's RT throttling then stalls both for tens of ms)
            user_sync = sync_loop(bus, dict(targets), PERIOD_S, n_sync, spin_s=0.0 if rt_priority else 3e-4)
        finally:
            if rt_priority:
                set_priority(os.getpid(), 0)
        time.sleep(0.2)
        wall, m1 = time.perf_counter() - t0, time.monotonic()
        out["serve_cpu_percent"] = 100.0 * (cpu_seconds(proc.pid) - cpu0) / wall
        out["child_cpu_percent"] = 100.0 * (_cpu_of(children) - child0) / wall
        out["child_processes"] = len(children)
        out["serve_threads"] = {k: round(100 * v["cpu_share"], 1)
                                for k, v in schedstat_delta(st0, thread_schedstat(proc.pid), wall).items()}
        out["serve_thread_count"] = _threads(proc.pid)
        frames1 = [t.evaluate(probe) for t in tabs]
        overruns1 = _late_cycles(bus, reply)
        out["window_overruns"] = None if None in (overruns0, overruns1) else overruns1 - overruns0
        if tabs:
            out["client_fps"] = [round((b[0] - a[0]) / wall, 1) for a, b in zip(frames0, frames1, strict=True)]
            out["client_samples_per_s"] = [round((b[1] - a[1]) / wall) for a, b in zip(frames0, frames1,
                                                                                          strict=True)]
            out["client_gaps"] = [b[2] for b in frames1]
        if clients:
            for c, _ in clients:  # back to a normal share of the CPU to write their results, then stop
                with contextlib.suppress(OSError):
                    os.sched_setscheduler(c.pid, os.SCHED_OTHER, os.sched_param(0))
                    os.setpriority(os.PRIO_PROCESS, c.pid, 0)
                c.send_signal(signal.SIGTERM)
            got = []
            for c, path in clients:
                c.wait(120)
                got.append(json.loads(path.read_text()))
            rates = [_window_rates(g["recv"], m0, m1) for g in got]
            out["client_messages_per_s"] = [round(r[0], 1) for r in rates]
            out["client_samples_per_s"] = [round(r[1]) for r in rates]
            out["client_gaps"] = [g["gaps"] for g in got]
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
        for c, _ in clients:
            if c.poll() is None:
                c.kill()
                c.wait()
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
    [us of this thread's CPU time per cycle]; and the server process' cost of draining (converting) the
    cycles' samples; and one call of the hook alone (``hook_call_us``, the time of an empty call taken off)."""
    import timeit

    from virtualaxis.config import load_axis_config
    from virtualaxis.drive.core import Drive
    from virtualaxis.services.http.ring import LongRing, PageBlock, segment_size

    drive = Drive(load_axis_config(REPO / CONFIG))
    drive.write_object(0x6060, 0, 8)
    for cw in (6, 7, 15):
        drive.write_object(0x6040, 0, cw)
    block = PageBlock(memoryview(bytearray(segment_size(1))), 0)  # (as in shared memory: a plain buffer)
    block.set_units(drive)
    ring = LongRing(block, drive.cycle_s, 60.0)
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
        drive.add_cycle_hook(block.hook)
        with_page, drain_us = run(16)
        best["with"] = min(best["with"], with_page)
        drain = min(drain, drain_us)
        drive.remove_cycle_hook(block.hook)
    hook = block.hook
    calls = 100_000
    call_us = min(timeit.repeat(lambda: hook(drive), number=calls, repeat=repeats)) / calls * 1e6
    empty_us = min(timeit.repeat(lambda: None, number=calls, repeat=repeats)) / calls * 1e6
    return {"hook_call_us": call_us - empty_us, "cycle_us_without_page": best["without"],
            "cycle_us_with_page": best["with"],
            "hook_us": best["with"] - best["without"], "ratio": best["with"] / best["without"],
            "drain_us_per_cycle": drain}


#: the measures of the drive's cycle whose shift against ``off`` the benchmark tests
SHIFT_KEYS = ("latency_us_p50", "latency_us_p99", "window_overruns", "late")


def _shifts(results: list[dict], phases: list[str]) -> dict:
    """Per page phase and measure: the shift of the median over the rounds against the ``off`` phase of the same
    code (``phase - off``) and the two-sided Mann-Whitney U p-value of the rounds of the two (small: the rounds of
    the phase differ from those of ``off`` beyond their scatter; needs 4+ rounds to get below 0.05)."""
    from scipy.stats import mannwhitneyu

    out = {}
    for p in phases:
        kind, _, code = p.partition("@")
        ref = f"off@{code}" if code else "off"
        if kind == "off" or ref not in phases:
            continue
        out[p] = {"reference": ref}
        for key in SHIFT_KEYS:
            a = [r[key] for r in results if r["phase"] == p and r.get(key) is not None]
            b = [r[key] for r in results if r["phase"] == ref and r.get(key) is not None]
            if a and b:
                out[p][key] = {"shift": float(np.median(a) - np.median(b)),
                               "p_value": float(mannwhitneyu(a, b, alternative="two-sided").pvalue)}
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="per phase")
    ap.add_argument("--rounds", type=int, default=2, help="passes over the phases")
    ap.add_argument("--phases", default="off,streams,browser", help="comma-separated: off, streams, browser, page10")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--sched-idle", action="store_true",
                    help="the clients (WebSocket processes, Chromium) at SCHED_IDLE instead of nice 19")
    ap.add_argument("--hook-cost", action="store_true", help="only the in-process cost of the page's cycle hook")
    ap.add_argument("--rt-priority", type=int, default=0, metavar="N",
                    help="serve (--rt-priority N) and this master's SYNC loop at SCHED_FIFO N; the clients stay "
                         "at their priority (the page's server process leaves real time on its own)")
    ap.add_argument("--pin", default=None, metavar="DRIVE_CPUS:LOAD_CPUS",
                    help="e.g. 1:0 -- serve's runtime + CAN receive threads on DRIVE_CPUS, the rest of the run "
                         "(page server, clients, browser, master) on LOAD_CPUS")
    ap.add_argument("--code", action="append", default=[], metavar="NAME=SRC",
                    help="run each phase with PYTHONPATH=SRC, once per --code (A/B of two source trees)")
    ap.add_argument("--ws-client", metavar="URL", help=argparse.SUPPRESS)  # one client process of `streams`
    opts = ap.parse_args()
    if opts.sched_idle:
        os.environ["BENCH_SCHED_IDLE"] = "1"  # (inherited by the client processes)
    drive_cpus = load_cpus = None
    if opts.pin:
        d, _, lo = opts.pin.partition(":")
        try:
            drive_cpus, load_cpus = {int(c) for c in d.split(",")}, {int(c) for c in lo.split(",")}
        except ValueError:
            ap.error(f"--pin {opts.pin!r}: expected DRIVE_CPUS:LOAD_CPUS, e.g. 1:0")
        os.environ["BENCH_LOAD_CPUS"] = ",".join(map(str, sorted(load_cpus)))  # (the clients, Chromium)
        os.sched_setaffinity(0, load_cpus)  # the master is another machine of the rig: not on the drive's CPU
    if opts.ws_client:
        return ws_client(opts.ws_client, opts.json)
    if opts.hook_cost:
        res = hook_cost()
        print(json.dumps(res | {"machine": machine_info()}, indent=1))
        return 0
    phases = [p.strip() for p in opts.phases.split(",") if p.strip()]
    unknown = sorted(set(phases) - {"off", "streams", "browser", "page10"})
    if unknown:
        ap.error(f"--phases: unknown {', '.join(unknown)} (off, streams, browser, page10)")
    import tempfile

    codes: list[tuple[str, str | None]] = []
    for item in opts.code:
        name, sep, src = item.partition("=")
        if not sep or not name or not (Path(src) / "virtualaxis" / "__init__.py").is_file():
            ap.error(f"--code {item!r}: expected NAME=SRC with SRC/virtualaxis/__init__.py")
        codes.append((name, str(Path(src).resolve())))
    labels = [f"{p}@{c}" for p in phases for c, _ in codes] if codes else phases
    results = []
    jitter = [host_jitter(rt_priority=opts.rt_priority)]  # the host's own tail, before and after the rounds
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(opts.rounds):
            for phase in phases:
                for name, src in codes or [(None, None)]:
                    res = run_phase(phase, opts.seconds, free_port(), Path(tmp), src, opts.rt_priority,
                                    drive_cpus, load_cpus)
                    res["round"] = r
                    res["phase"] = f"{phase}@{name}" if name else phase
                    results.append(res)
                    print(json.dumps({k: v for k, v in res.items() if k != "per_node"}), flush=True)
    phases = labels
    jitter.append(host_jitter(rt_priority=opts.rt_priority))

    def med(phase: str, key: str) -> float:
        vals = [r[key] for r in results if r["phase"] == phase and r.get(key) is not None]
        return float(np.median(vals)) if vals else float("nan")

    summary = {"machine": machine_info(), "rounds": results}
    width = max(12, *(len(p) + 2 for p in phases))
    print(f"\n{'':24s}" + "".join(f"{p:>{width}s}" for p in phases))
    for key in ("latency_us_p50", "latency_us_p99", "latency_us_max", "window_overruns", "missed", "late",
                "serve_cpu_percent", "child_cpu_percent", "serve_thread_count", "loadavg_1min"):
        vals = {p: med(p, key) for p in phases}
        summary[key] = vals
        print(f"{key:24s}" + "".join(f"{vals[p]:{width}.1f}" for p in phases))
    summary["host_jitter"] = jitter
    print("host (plain-Python workload paced at 1 ms, before / after): p99 "
          + " / ".join(f"{j['work_us_p99_paced']:.0f} us = {j['paced_p99_over_p50']:.1f}x its back-to-back p50"
                       for j in jitter))
    summary["shift_vs_off"] = shifts = _shifts(results, phases)
    for p, by_key in shifts.items():
        print(f"{p} - {by_key['reference']}: " + ", ".join(
            f"{key} {v['shift']:+.0f} (p = {v['p_value']:.2f})" for key, v in by_key.items() if key != "reference"))
    for p in phases:
        rs = [r for r in results if r["phase"] == p]
        rate = [x for r in rs for x in r.get("client_samples_per_s", [])]
        if rate:
            fps = [x for r in rs for x in r.get("client_fps", r.get("client_messages_per_s", []))]
            unit = "frames drawn/s" if any("client_fps" in r for r in rs) else "messages/s"
            print(f"{p}: per client {unit} {min(fps):.0f}-{max(fps):.0f}, samples/s {min(rate)}-{max(rate)}, "
                  f"gaps {sum(g for r in rs for g in r.get('client_gaps', []))}")
    if opts.json:
        Path(opts.json).write_text(json.dumps(summary, indent=2, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
