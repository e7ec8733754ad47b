"""Random and hostile CAN traffic against a served drive: does anything die without a sign?

Each run starts ``virtualaxis serve`` (real-time pacing, ``--allow-fault-injection`` off) in a child process on a
host-local ``udp_multicast`` group (hop_limit 0) and sends it, for ``--seconds``, a mix of frames chosen at random:

- **legal writes**: SDO expedited downloads of random values *within* the EDS limits to every writable object
  (among them the external force 0x2011 and the plant parameters that once drove a NaN into the drive cycle),
  the enable sequence 0x06/0x07/0x0F, modes of operation, targets;
- **bad writes**: values outside the limits, NaN / inf / denormal REAL32 bit patterns, wrong sizes;
- RPDOs with random data, SYNC (with and without a counter), NMT commands (start, stop, pre-operational, reset
  communication, reset node), random SDO requests (block and segmented commands included), random COB-IDs and
  lengths.

Every ``--probe-interval`` s the fuzzer pauses and checks that the drive still answers: an SDO upload of 0x1000
and 0x6041 (with retries for a request that crossed a fuzz frame). At the end: the run's EMCY codes, the serve
process' exit status and its final JSON (``runtime.thread_error``, ``drive_exceptions``).

A run **fails** when serve died, exited non-zero, reported a stopped runtime thread, or a probe went
unanswered for ``--probe-timeout`` s. The figures are printed and written with ``--json``.

    python benchmarks/fuzz_serve.py --runs 5 --seconds 30 --json fuzz.json
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import can
import canopen
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _master import machine_info  # noqa: E402

from virtualaxis.master import DEFAULT_EDS  # noqa: E402

CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
NODE = 1
SIZES = {canopen.objectdictionary.BOOLEAN: 1, canopen.objectdictionary.INTEGER8: 1,
         canopen.objectdictionary.UNSIGNED8: 1, canopen.objectdictionary.INTEGER16: 2,
         canopen.objectdictionary.UNSIGNED16: 2, canopen.objectdictionary.INTEGER32: 4,
         canopen.objectdictionary.UNSIGNED32: 4, canopen.objectdictionary.REAL32: 4}
FMT = {canopen.objectdictionary.BOOLEAN: "<B", canopen.objectdictionary.INTEGER8: "<b",
       canopen.objectdictionary.UNSIGNED8: "<B", canopen.objectdictionary.INTEGER16: "<h",
       canopen.objectdictionary.UNSIGNED16: "<H", canopen.objectdictionary.INTEGER32: "<i",
       canopen.objectdictionary.UNSIGNED32: "<I", canopen.objectdictionary.REAL32: "<f"}
TYPE_RANGE = {"<B": (0, 255), "<b": (-128, 127), "<h": (-32768, 32767), "<H": (0, 65535),
              "<i": (-2**31, 2**31 - 1), "<I": (0, 2**32 - 1)}


def writable_entries(eds: str) -> list:
    od = canopen.import_od(eds, NODE)
    out = []
    for obj in od.values():
        subs = obj.values() if isinstance(obj, (canopen.objectdictionary.ODRecord, canopen.objectdictionary.ODArray)) \
            else [obj]
        for var in subs:
            if var.writable and var.data_type in FMT:
                out.append(var)
    return out


def in_range_value(var, rng: random.Random):
    fmt = FMT[var.data_type]
    if fmt == "<f":
        lo = var.min if var.min is not None else -1e6
        hi = var.max if var.max is not None else 1e6
        return rng.choice([lo, hi, 0.0, rng.uniform(lo, hi), rng.uniform(lo, hi) * 1e-6])
    lo, hi = TYPE_RANGE[fmt]
    lo = var.min if var.min is not None else lo
    hi = var.max if var.max is not None else hi
    return rng.choice([lo, hi, 0, rng.randint(int(lo), int(hi))]) if lo <= 0 <= hi else rng.randint(int(lo), int(hi))


def bad_value_bytes(var, rng: random.Random) -> bytes:
    fmt = FMT[var.data_type]
    if fmt == "<f":
        return struct.pack("<I", rng.choice([0x7FC00000, 0x7F800000, 0xFF800000, 0x00000001, 0x7F7FFFFF,
                                             rng.getrandbits(32)]))
    return rng.getrandbits(8 * SIZES[var.data_type]).to_bytes(SIZES[var.data_type], "little")


def sdo_download(var, payload: bytes) -> can.Message:
    n = len(payload)
    cmd = 0x23 | ((4 - n) << 2) if n <= 4 else 0x21
    data = bytes([cmd, var.index & 0xFF, var.index >> 8, var.subindex]) + payload[:4].ljust(4, b"\0")
    return can.Message(arbitration_id=0x600 + NODE, data=data, is_extended_id=False)


def random_frame(rng: random.Random, entries: list) -> can.Message:
    r = rng.random()
    msg = lambda cob, data: can.Message(arbitration_id=cob, data=bytes(data), is_extended_id=False)  # noqa: E731
    if r < 0.35:  # a legal, in-range write
        var = rng.choice(entries)
        try:
            payload = struct.pack(FMT[var.data_type], in_range_value(var, rng))
        except struct.error:
            payload = bad_value_bytes(var, rng)
        return sdo_download(var, payload)
    if r < 0.45:  # an out-of-range / non-finite write
        var = rng.choice(entries)
        return sdo_download(var, bad_value_bytes(var, rng))
    if r < 0.52:  # enable, modes, targets by SDO
        choice = rng.randrange(4)
        if choice == 0:
            return msg(0x600 + NODE, [0x2B, 0x40, 0x60, 0, rng.choice([0x06, 0x07, 0x0F, 0x1F, 0x80, 0x00, 0x02]), 0,
                                      0, 0])
        if choice == 1:
            return msg(0x600 + NODE, [0x2F, 0x60, 0x60, 0, rng.choice([1, 3, 4, 6, 8, 9, 10, 0, 0xFF]), 0, 0, 0])
        return msg(0x600 + NODE, [0x23, rng.choice([0x7A, 0xFF, 0x71]), 0x60, 0, *rng.randbytes(4)])
    if r < 0.67:  # PDOs with random data (RPDO1..4) and SYNC
        if rng.random() < 0.5:
            return msg(rng.choice([0x200, 0x300, 0x400, 0x500]) + NODE, rng.randbytes(rng.randint(0, 8)))
        return msg(0x80, rng.randbytes(rng.choice([0, 0, 1])))
    if r < 0.70:  # NMT
        return msg(0x000, [rng.choice([0x01, 0x02, 0x80, 0x82, 0x81]), rng.choice([0, NODE])])
    if r < 0.85:  # random SDO requests
        return msg(0x600 + NODE, rng.randbytes(rng.choice([8, 8, 8, rng.randint(0, 8)])))
    return msg(rng.randrange(0x800), rng.randbytes(rng.randint(0, 8)))  # anything


class Probe(can.Listener):
    """Collects SDO responses and EMCY codes of the node."""

    def __init__(self):
        self.lock = threading.Lock()
        self.sdo: list[bytes] = []
        self.emcy: Counter = Counter()
        self.heartbeats = 0

    def on_message_received(self, m: can.Message) -> None:
        with self.lock:
            if m.arbitration_id == 0x580 + NODE:
                self.sdo.append(bytes(m.data))
            elif m.arbitration_id == 0x80 + NODE and len(m.data) >= 2:
                self.emcy[f"0x{m.data[0] | m.data[1] << 8:04X}"] += 1
            elif m.arbitration_id == 0x700 + NODE:
                self.heartbeats += 1


def probe(bus, listener: Probe, index: int, timeout_s: float) -> float | None:
    """SDO upload of ``index``:0 until answered (retries every 0.1 s); seconds it took or None."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout_s:
        with listener.lock:
            listener.sdo.clear()
        bus.send(can.Message(arbitration_id=0x600 + NODE, data=bytes([0x40, index & 0xFF, index >> 8, 0, 0, 0, 0, 0]),
                             is_extended_id=False))
        t_try = time.perf_counter()
        while time.perf_counter() - t_try < 0.1:
            with listener.lock:
                hit = [d for d in listener.sdo if d[1] | d[2] << 8 == index and d[0] in (0x43, 0x47, 0x4B, 0x4F,
                                                                                     0x41, 0x80)]
            if hit:
                return time.perf_counter() - t0
            time.sleep(0.002)
    return None


def one_run(run: int, seconds: float, probe_interval: float, probe_timeout: float, seed: int, entries: list) -> dict:
    rng = random.Random(seed * 1000 + run)
    group = f"239.74.{rng.randint(100, 250)}.{rng.randint(1, 250)}"
    port = rng.randint(46000, 49000)
    spec = f"udp_multicast:{group},port={port}"
    tmp = Path(tempfile.mkdtemp(prefix="fuzz_serve_"))
    proc = subprocess.Popen([*CLI, "serve", "--can", spec, "--node-id", str(NODE), "--status-interval", "0",
                             "--json", str(tmp / "serve.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=str(ROOT), env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        return {"run": run, "failed": True, "why": f"serve did not start: {line!r} {proc.stderr.read()[-2000:]}"}
    bus = can.Bus(interface="udp_multicast", channel=group, port=port, hop_limit=0, receive_own_messages=False)
    listener = Probe()
    notifier = can.Notifier(bus, [listener])
    sent, probes, unanswered, worst = 0, 0, 0, 0.0
    t_end = time.monotonic() + seconds
    next_probe = time.monotonic() + probe_interval
    try:
        while time.monotonic() < t_end and proc.poll() is None:
            for _ in range(20):
                bus.send(random_frame(rng, entries))
                sent += 1
            time.sleep(0.01)  # ~2000 frames/s
            if time.monotonic() >= next_probe:
                next_probe += probe_interval
                time.sleep(0.05)  # let the fuzz frames in flight be answered
                # NMT Stopped answers no SDO (CiA 301), and the fuzzer sends NMT Stop: start the node first
                bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, NODE]), is_extended_id=False))
                time.sleep(0.01)
                for index in (0x1000, 0x6041):
                    dt = probe(bus, listener, index, probe_timeout)
                    probes += 1
                    if dt is None:
                        unanswered += 1
                    else:
                        worst = max(worst, dt)
        alive = proc.poll() is None
        bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, NODE]), is_extended_id=False))
        time.sleep(0.01)
        final = probe(bus, listener, 0x1000, probe_timeout) if alive else None
    finally:
        notifier.stop()
        bus.shutdown()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    summary = json.loads((tmp / "serve.json").read_text()) if (tmp / "serve.json").exists() else {}
    rt = summary.get("runtime", {})
    res = {
        "run": run,
        "frames_sent": sent,
        "frames_per_s": sent / seconds,
        "probes": probes,
        "probes_unanswered": unanswered,
        "probe_worst_ms": worst * 1e3,
        "alive_at_end": alive,
        "answered_at_end": final is not None,
        "serve_exit": proc.returncode,
        "thread_error": (rt.get("thread_error") or "")[-500:],
        "drive_exceptions": rt.get("drive_exceptions"),
        "emcy": dict(listener.emcy.most_common()),
        "traceback_in_stderr": "Traceback" in err,
        "stderr_tail": err[-1500:] if err else "",
    }
    res["failed"] = bool(not alive or proc.returncode != 0 or res["thread_error"] or unanswered
                         or final is None)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--probe-interval", type=float, default=1.0)
    ap.add_argument("--probe-timeout", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    entries = writable_entries(str(DEFAULT_EDS))
    runs = []
    for r in tqdm(range(a.runs), desc="fuzz runs", unit="run"):
        res = one_run(r, a.seconds, a.probe_interval, a.probe_timeout, a.seed, entries)
        runs.append(res)
        print(f"run {r}: {'FAIL' if res['failed'] else 'ok'}  frames {res.get('frames_sent', 0)} "
              f"({res.get('frames_per_s', 0):.0f}/s), probes {res.get('probes', 0)} unanswered "
              f"{res.get('probes_unanswered')} worst {res.get('probe_worst_ms', 0):.1f} ms, serve exit "
              f"{res.get('serve_exit')}, drive exceptions caught {res.get('drive_exceptions')}, thread error "
              f"{'yes' if res.get('thread_error') else 'no'}, EMCY {res.get('emcy')}", flush=True)
        if res.get("why"):
            print("  ", res["why"])
    failed = sum(r["failed"] for r in runs)
    out = {"machine": machine_info(), "writable_entries": len(entries), "seconds": a.seconds, "runs": runs,
           "failed_runs": failed}
    print(f"{failed} of {a.runs} runs failed ({len(entries)} writable EDS entries fuzzed)")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=2))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
