"""Do the side channels disturb the drive? SYNC -> TPDO latency and missed cycles of a CSP move at 1 ms SYNC,
without and with the side-channel load, in the same run; Modbus response times under that load.

Each phase starts its own ``virtualaxis serve`` process (real-time pacing, 1 ms drive cycle) on a host-local
``udp_multicast`` bus (hop_limit 0); this process is the CANopen master (SYNC + a synchronous CSP target RPDO
every 1 ms, TPDO2 = statusword + position answered on every SYNC, a 20 mm sine at 0.5 Hz).

- phase ``off``: ``serve`` without side channels;
- phase ``load``: ``serve --modbus ... --mqtt ...`` (telemetry 100 Hz in batches of 10 to a mosquitto broker
  started here on a free loopback port, read by a paho subscriber in this process) and **ten Modbus TCP clients**
  (ten processes), each polling 50 registers (40110-40121 and 40340-40377: two FC03 requests) at 100 Hz; a
  client a whole period behind skips the missed polls (counted), so ``polls/s`` is the load delivered.

With ``--rt-priority N`` serve and the master run at SCHED_FIFO N, the load side (clients, serve's Modbus server
process, mosquitto) at ``--load-priority`` (10) below it: on a shared machine other jobs would otherwise starve
the load generator and the drive would be measured without the load it is meant to carry.

Phases alternate (off, load, off, load, ...; ``--rounds``) so that drifting machine load hits both alike.
Latency = TPDO receive time minus SYNC send time (both in this process). Missed = SYNCs without a TPDO.

    python benchmarks/bench_side_channels.py                    # 2 rounds of 30 s per phase
    python benchmarks/bench_side_channels.py --seconds 10 --rounds 1 --rt-priority 20
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import numpy as np
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
POLL_RANGES = ((40110, 12), (40340, 38))  # 50 registers per poll
CLIENTS = 10


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.02)


# ------------------------------------------------------------------------------------ Modbus load (subprocess)
def set_priority(pid: int, priority: int) -> None:
    """SCHED_FIFO ``priority`` for ``pid`` and all its threads (0: SCHED_OTHER)."""
    policy, param = (os.SCHED_FIFO, priority) if priority else (os.SCHED_OTHER, 0)
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setscheduler(int(tid), policy, os.sched_param(param))
        except OSError:
            pass


def children(pid: int) -> list[int]:
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out += [int(c) for c in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()]
        except OSError:
            pass
    return out


def modbus_load(
    port: int, clients: int, rate_hz: float, seconds: float, out: str, priority: int = 0, start_unix: float = 0.0
) -> None:
    """``clients`` threads, each with its own TCP connection, polling POLL_RANGES at ``rate_hz``."""
    from pymodbus.client import ModbusTcpClient

    # in a plant the clients run on other machines: here below the drive's priority (or at normal priority)
    policy, param = (os.SCHED_FIFO, priority) if priority else (os.SCHED_OTHER, 0)
    os.sched_setscheduler(0, policy, os.sched_param(param))
    results: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    late = [0] * clients
    start = time.perf_counter() + max(0.2, start_unix - time.time())

    def worker(i: int) -> None:
        c = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        c.connect()
        period = 1.0 / rate_hz
        nxt = start + i * period / clients
        end = start + seconds
        while nxt < end:
            now = time.perf_counter()
            if now < nxt:
                time.sleep(nxt - now)
            elif now - nxt > period:  # a whole period behind: skip the missed polls (counted), no catch-up burst
                skipped = int((now - nxt) / period)
                late[i] += skipped
                nxt += skipped * period
                continue
            for number, count in POLL_RANGES:
                t0 = time.perf_counter()
                r = c.read_holding_registers(number - 40001, count=count, device_id=1)
                results[i].append(time.perf_counter() - t0)
                if r.isError():
                    errors[i] += 1
            nxt += period
        c.close()

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    np.save(out + ".npy", np.concatenate([np.array(r) for r in results]) * 1e6)
    Path(out).write_text(json.dumps({"errors": int(sum(errors)), "skipped_polls": int(sum(late))}))


def modbus_summary(outs: list[str], seconds: float) -> dict:
    """Response times and delivered load of all client processes."""
    rt = np.concatenate([np.load(o + ".npy") for o in outs])
    counters = [json.loads(Path(o).read_text()) for o in outs]
    return {
        "clients": len(outs),
        "requests": int(rt.size),
        "errors": sum(c["errors"] for c in counters),
        "skipped_polls": sum(c["skipped_polls"] for c in counters),  # deadlines missed by a whole period
        "polls_per_s": rt.size / len(POLL_RANGES) / seconds,
        "response_us_p50": float(np.percentile(rt, 50)),
        "response_us_p99": float(np.percentile(rt, 99)),
        "response_us_max": float(rt.max()),
    }


# ------------------------------------------------------------------------------------ the master
class Tpdo(can.Listener):
    def __init__(self, cob: int, sdo_cob: int):
        self.cob = cob
        self.sdo_cob = sdo_cob
        self.times: list[float] = []
        self.reply = threading.Event()
        self.last: can.Message | None = None

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == self.cob:
            self.times.append(msg.timestamp)
        elif msg.arbitration_id == self.sdo_cob:
            self.last = msg
            self.reply.set()


def sdo(bus: can.BusABC, rx: Tpdo, node: int, index: int, sub: int = 0, value: int | None = None, size: int = 4):
    rx.reply.clear()
    if value is None:
        data = bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])
    else:
        cmd = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
        data = bytes([cmd, index & 0xFF, index >> 8, sub]) + int(value).to_bytes(4, "little", signed=value < 0)
    bus.send(can.Message(arbitration_id=0x600 + node, data=data, is_extended_id=False))
    if not rx.reply.wait(2.0):
        raise RuntimeError(f"SDO timeout 0x{index:04X}:{sub}")
    if rx.last.data[0] == 0x80:
        raise RuntimeError(f"SDO abort 0x{int.from_bytes(rx.last.data[4:8], 'little'):08X} on 0x{index:04X}")
    return int.from_bytes(rx.last.data[4:8], "little")


class Mosquitto:
    def __init__(self, workdir: Path):
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        self.port = free_port()
        conf = workdir / "mosquitto.conf"
        conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n")
        self.proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_port(self.port)

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=10)


class TelemetryCounter:
    def __init__(self, port: int):
        import paho.mqtt.client as mqtt

        self.batches = 0
        self.samples = 0
        self.c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe("virtualaxis/+/+/telemetry", qos=0)
        self.c.on_message = self._on
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()

    def _on(self, client, userdata, m):
        self.batches += 1
        self.samples += len(json.loads(m.payload)["samples"])

    def stop(self):
        self.c.loop_stop()
        self.c.disconnect()


def run_phase(
    load: bool, seconds: float, port: int, broker: Mosquitto | None, rt_priority: int, load_priority: int, tmp: Path
) -> dict:
    spec = f"udp_multicast:239.74.163.3,port={port}"
    node = 1
    summary = tmp / f"serve-{port}.json"
    args = [*CLI, "serve", "--can", spec, "--node-id", str(node), "--status-interval", "0",
            "--duration", str(seconds + 60), "--json", str(summary)]
    mb_port = free_port()
    if load:
        args += ["--modbus", f"127.0.0.1:{mb_port}", "--mqtt", f"mqtt://127.0.0.1:{broker.port}", "--machine", "bench"]
    if rt_priority:
        args += ["--rt-priority", str(rt_priority)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise RuntimeError(f"serve did not start: {line} {proc.stderr.read()}")
    if load and rt_priority:
        proc.stdout.readline()  # "modbus: ..." (the server process runs by then)
        for child in children(proc.pid):  # serve's Modbus server process: the clients' side, below the drive
            set_priority(child, load_priority)
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.3", port=port, hop_limit=0)
    rx = Tpdo(0x280 + node, 0x580 + node)
    notifier = can.Notifier(bus, [rx], timeout=0.05)
    loader = telemetry = None
    out: dict = {"phase": "load" if load else "off", "seconds": seconds}
    try:
        sdo(bus, rx, node, 0x6060, value=8, size=1)
        sdo(bus, rx, node, 0x6065, value=50_000)
        sdo(bus, rx, node, 0x1401, 2, value=1, size=1)
        sdo(bus, rx, node, 0x1801, 2, value=1, size=1)
        for tpdo, base in ((0x1800, 0x180), (0x1802, 0x380), (0x1803, 0x480)):
            sdo(bus, rx, node, tpdo, 1, value=0x80000000 | (base + node))
        bus.send(can.Message(arbitration_id=0x000, data=bytes([0x01, node]), is_extended_id=False))
        for cw in (0x06, 0x07, 0x0F):
            sdo(bus, rx, node, 0x6040, value=cw, size=2)
        x0 = int.from_bytes(sdo(bus, rx, node, 0x6064).to_bytes(4, "little"), "little", signed=True)
        if load:
            telemetry = TelemetryCounter(broker.port)
            # ten clients = ten processes (each its own interpreter, as separate client machines would be)
            outs = [str(tmp / f"modbus-{port}-{i}.json") for i in range(CLIENTS)]
            t_start = time.time() + 3.0  # all clients start polling together, once their imports are done
            loader = [
                subprocess.Popen([sys.executable, __file__, "--modbus-load", str(mb_port), str(seconds), o,
                                  "--load-priority", str(load_priority if rt_priority else 0),
                                  "--load-start", f"{t_start + i * 1e-3:.6f}"])
                for i, o in enumerate(outs)
            ]
            time.sleep(max(0.0, t_start - time.time()) + 0.1)  # clients polling
        rx.times.clear()
        n_sync = int(seconds / 1e-3)
        sync_times = np.zeros(n_sync)
        t_next = time.perf_counter() + 0.01
        sync_msg = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
        tel0 = telemetry.samples if telemetry else 0
        for k in tqdm(range(n_sync), desc=f"phase {out['phase']}", unit="sync", mininterval=1, leave=False):
            while True:
                left = t_next - time.perf_counter()
                if left <= 0:
                    break
                time.sleep(left - 3e-4 if left > 4e-4 else 0)
            target = x0 + int(20_000 * np.sin(2 * np.pi * 0.5 * k * 1e-3))
            bus.send(can.Message(arbitration_id=0x300 + node,
                                 data=(0x0F).to_bytes(2, "little") + target.to_bytes(4, "little", signed=True),
                                 is_extended_id=False))
            sync_times[k] = time.time()
            bus.send(sync_msg)
            t_next += 1e-3
        time.sleep(0.2)
        times = np.array(rx.times)
        if len(times) == n_sync:
            lat = (times - sync_times) * 1e6
        else:
            idx = np.minimum(np.searchsorted(times, sync_times), max(len(times) - 1, 0))
            lat = (times[idx] - sync_times) * 1e6 if len(times) else np.array([np.nan])
        out.update(
            syncs=n_sync,
            tpdos=int(len(times)),
            missed_cycles=int(n_sync - len(times)),
            late_tpdos=int(np.count_nonzero(lat > 1000)),
            latency_us_p50=float(np.percentile(lat, 50)),
            latency_us_p99=float(np.percentile(lat, 99)),
            latency_us_max=float(np.max(lat)),
        )
        if telemetry is not None:
            out["telemetry_samples_per_s"] = (telemetry.samples - tel0) / seconds
            out["telemetry_batches"] = telemetry.batches
        if loader is not None:
            for lp in loader:
                lp.wait(timeout=seconds + 60)
            out["modbus"] = modbus_summary(outs, seconds)
    finally:
        if telemetry is not None:
            telemetry.stop()
        for lp in loader or []:
            if lp.poll() is None:
                lp.kill()
        notifier.stop()
        bus.shutdown()
        proc.send_signal(signal.SIGINT)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    if summary.exists():
        s = json.loads(summary.read_text())
        out["drive_overruns"] = s["runtime"]["overruns"]
        if "mqtt" in s:
            out["mqtt"] = next(iter(s["mqtt"].values()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="per phase")
    ap.add_argument("--rounds", type=int, default=2, help="off/load pairs")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of serve and the master")
    ap.add_argument("--load-priority", type=int, default=10,
                    help="with --rt-priority: SCHED_FIFO priority of the load side (Modbus clients, serve's Modbus "
                    "server process, mosquitto), below the drive's, so that other jobs on a shared machine do not "
                    "starve the load generator (0: normal priority)")
    ap.add_argument("--load-start", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "bench_side_channels.json"))
    ap.add_argument("--modbus-load", nargs=3, metavar=("PORT", "SECONDS", "OUT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.modbus_load:
        modbus_load(int(args.modbus_load[0]), 1, 100.0, float(args.modbus_load[1]), args.modbus_load[2],
                    args.load_priority, args.load_start)
        return 0
    if args.rt_priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
    results = []
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        broker = Mosquitto(tmp)
        if args.rt_priority:
            set_priority(broker.proc.pid, args.load_priority)
        try:
            for r in range(args.rounds):
                for load in (False, True):
                    port = 46000 + os.getpid() % 400 + 2 * r + int(load)
                    results.append(
                        run_phase(load, args.seconds, port, broker, args.rt_priority, args.load_priority, tmp)
                    )
        finally:
            broker.stop()
    machine = {"nproc": os.cpu_count(), "cpu": _cpu_model(), "python": platform.python_version(),
               "load_average_at_end": os.getloadavg()}
    print(f"\nmachine: {machine['nproc']} cores, {machine['cpu']}, Python {machine['python']}, "
          f"load average {machine['load_average_at_end']}")
    print(f"{'phase':>6} {'p50 us':>8} {'p99 us':>8} {'max us':>9} {'missed':>7} {'late':>6} {'overruns':>8} "
          f"{'MB p50 us':>9} {'MB p99 us':>9} {'polls/s':>8} {'tele/s':>7}")
    for r in results:
        mb = r.get("modbus", {})
        print(f"{r['phase']:>6} {r['latency_us_p50']:>8.0f} {r['latency_us_p99']:>8.0f} {r['latency_us_max']:>9.0f} "
              f"{r['missed_cycles']:>7} {r['late_tpdos']:>6} {r.get('drive_overruns', -1):>8} "
              f"{mb.get('response_us_p50', float('nan')):>9.0f} {mb.get('response_us_p99', float('nan')):>9.0f} "
              f"{mb.get('polls_per_s', 0):>8.0f} {r.get('telemetry_samples_per_s', 0):>7.0f}")
    off = [r for r in results if r["phase"] == "off"]
    on = [r for r in results if r["phase"] == "load"]
    summary = {
        "p99_off_us_median": float(np.median([r["latency_us_p99"] for r in off])),
        "p99_load_us_median": float(np.median([r["latency_us_p99"] for r in on])),
        "missed_off": sum(r["missed_cycles"] for r in off),
        "missed_load": sum(r["missed_cycles"] for r in on),
    }
    summary["p99_shift_us"] = summary["p99_load_us_median"] - summary["p99_off_us_median"]
    print(f"p99 off {summary['p99_off_us_median']:.0f} us, with load {summary['p99_load_us_median']:.0f} us "
          f"(shift {summary['p99_shift_us']:+.0f} us); missed cycles off {summary['missed_off']}, "
          f"load {summary['missed_load']}")
    Path(args.json).write_text(json.dumps({"machine": machine, "args": vars(args), "summary": summary,
                                           "results": results}, indent=2))
    print(f"wrote {args.json}")
    return 0


def _cpu_model() -> str:
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    sys.exit(main())
