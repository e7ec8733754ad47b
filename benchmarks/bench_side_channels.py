"""Do the side channels disturb the drive? SYNC -> TPDO latency and missed cycles of a CSP move at 1 ms SYNC,
without and with the side-channel load, in the same run; Modbus response times under that load; where each
latency accrues (hop timestamps) and which thread waited for a CPU (per-thread run-queue time).

Each phase starts its own ``virtualaxis serve`` process (real-time pacing, 1 ms drive cycle, ``--bitrate`` 0 by
default: the raw latency of the runtime, as ``bench_drive_latency.py``) on a host-local ``udp_multicast`` bus
(hop_limit 0); this process is the CANopen master (``_master.py``: SYNC + a synchronous CSP target RPDO every
1 ms, TPDO2 = statusword + position answered on every SYNC, a 20 mm sine at 0.5 Hz).

Phases (``--phases``, alternated ``--rounds`` times so that drifting machine load hits all alike):

- ``off``: ``serve`` without side channels;
- ``load``: ``serve --modbus ... --mqtt ...`` (telemetry 100 Hz in batches of 10 to a mosquitto broker started
  here on a free loopback port, counted by a paho subscriber in a process of its own) and **ten Modbus TCP
  clients** (ten processes), each polling 50 registers (40110-40121 and 40340-40377: two FC03 requests) at
  100 Hz; a client a whole period behind skips the missed polls (counted), so ``polls/s`` is the load delivered;
- ``modbus`` / ``mqtt``: only that half of the load (to separate the causes);
- ``ext``: ``serve`` without side channels while the ten Modbus clients poll a plain pymodbus server of their
  own (static registers): the machine carries the client load, ``serve`` none of it;
- ``idle``: ``serve --modbus --mqtt`` with nobody polling or subscribing (the side channels' own cost in serve);
- ``load-spb``, ``mqtt-spb``, ``idle-spb``: ``load``, ``mqtt``, ``idle`` with the MQTT side as Sparkplug B
  (``serve --sparkplug bench``; the subscriber counts the Position values of the DDATA); ``--sparkplug`` makes
  every MQTT phase Sparkplug B.
- ``opcua``: ``serve --opcua`` and one OPC UA subscriber (asyncua, a process of its own) monitoring
  :data:`OPCUA_ITEMS` (10 nodes of the axis) in a subscription of 100 ms publishing interval;
- ``all``: the ``load`` phase plus the ``opcua`` one;
- ``PHASE@ref`` (with ``--ref-src DIR``): PHASE with the ``serve`` of another virtualaxis source tree (e.g. a
  checkout of the main branch), for an A/B of two versions in the same run.

Priorities (``--rt-priority N``): ``serve`` **and the master** run at SCHED_FIFO N -- the master at the drive's
priority, so that it measures the drive and not its own starvation. The load side (clients, serve's Modbus
server process, mosquitto, the MQTT subscriber) runs at normal priority (``--load-priority 0``, the default;
clients of a real drive sit on other machines) or at SCHED_FIFO ``--load-priority`` below the drive.
``--pin DRIVE_CPUS:LOAD_CPUS`` (e.g. ``1:0``) pins serve's runtime and CAN receive threads to DRIVE_CPUS and
everything else of the run (serve's other threads, the side-channel processes, the clients, the broker and the
master, which in a rig is another machine) to LOAD_CPUS: an isolated-core deployment (docs/side-channels.md).

Latency = kernel receive timestamp of the TPDO in the master's socket minus that of the master's own SYNC as
looped back (the instant the SYNC was on the "wire", also the instant serve's socket got it); nothing of the
master's user-space receive or send path is in it. Missed = SYNCs without a TPDO; late = TPDOs after the next
SYNC. Hops (``serve --latency-probe``): SYNC wire -> serve's receive thread has it (``rx thread``) -> serve's
runtime thread sends the TPDO (``runtime``) -> TPDO in the master's socket (``back``); ``master send`` =
master's ``time.time()`` before ``send`` -> its SYNC on the wire (not part of the latency).

    python benchmarks/bench_side_channels.py --seconds 20 --rounds 2 --rt-priority 20
    python benchmarks/bench_side_channels.py --seconds 10 --rounds 1 --rt-priority 20 --phases off,modbus,mqtt,load
    python benchmarks/bench_side_channels.py --seconds 5 --rounds 3 --rt-priority 20 --modbus-client raw --json F
    python benchmarks/bench_side_channels.py --seconds 10 --rounds 2 --rt-priority 20 --phases off,load,load-spb
    python benchmarks/bench_side_channels.py --seconds 10 --rounds 2 --phases off,opcua,load,all
    python benchmarks/bench_side_channels.py --seconds 10 --rounds 2 --rt-priority 20 \
        --phases off,opcua,opcua@ref,all --ref-src ../main/src

``--modbus-client raw``: the ten clients pack their FC03 requests with ``struct`` on a plain socket (and check every
answer) instead of using pymodbus' client, which on a slow host costs 2.5x the CPU per request: the clients of a
real drive sit on other machines, so their own CPU here only takes CPU from what is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import can
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _master import (  # noqa: E402
    CLI,
    REPO,
    SYNC_COB,
    SdoReply,
    TpdoClock,
    children,
    free_port,
    latency_stats,
    machine_info,
    pair,
    percentiles_us,
    schedstat_delta,
    sdo,
    set_affinity,
    set_priority,
    setup_csp,
    sync_loop,
    thread_schedstat,
    wait_port,
)

POLL_RANGES = ((40110, 12), (40340, 38))  # 50 registers per poll
CLIENTS = 10
PERIOD_S = 1e-3
DRIVE_THREADS = ("runtime", "can-rx")  # serve's threads on the SYNC -> TPDO path (OS names, latency_probe)


# ------------------------------------------------------------------------------------ load side (subprocesses)
def _become_load(priority: int, cpus: set[int] | None) -> None:
    # in a plant the clients run on other machines: here at normal priority or FIFO below the drive
    policy, param = (os.SCHED_FIFO, priority) if priority else (os.SCHED_OTHER, 0)
    os.sched_setscheduler(0, policy, os.sched_param(param))
    if cpus:
        os.sched_setaffinity(0, cpus)


class RawModbusClient:
    """A lean Modbus TCP client (FC03 only: struct-packed MBAP + PDU on a plain socket) for ``--modbus-client
    raw``: the clients of a real drive sit on other machines, so on this host their own CPU is an artefact of the
    rig; this one costs a fraction of pymodbus' client per request. Checks every answer (transaction id, protocol
    0, unit, function, byte count) and counts exceptions and malformed answers as errors."""

    def __init__(self, host: str, port: int, timeout: float = 2.0):
        import socket
        import struct

        self._sock = socket.create_connection((host, port), timeout=timeout)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._req = struct.Struct(">HHHBBHH")
        self._tid = 0

    def _recv(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self._sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("server closed the connection")
            buf += chunk
        return buf

    def read_holding(self, address: int, count: int, unit: int) -> bool:
        """FC03 of ``count`` registers at PDU ``address``; True if a well-formed answer of ``count`` registers."""
        self._tid = (self._tid + 1) & 0xFFFF
        self._sock.sendall(self._req.pack(self._tid, 0, 6, unit, 3, address, count))
        head = self._recv(7)
        tid, proto, length = int.from_bytes(head[0:2], "big"), int.from_bytes(head[2:4], "big"), \
            int.from_bytes(head[4:6], "big")
        body = self._recv(length - 1)
        return (tid == self._tid and proto == 0 and head[6] == unit and body[0] == 3 and body[1] == 2 * count
                and len(body) == 2 + 2 * count)

    def close(self) -> None:
        self._sock.close()


def modbus_load(port: int, clients: int, rate_hz: float, seconds: float, out: str, start_unix: float = 0.0,
                kind: str = "pymodbus") -> None:
    """``clients`` threads, each with its own TCP connection, polling POLL_RANGES at ``rate_hz`` with pymodbus'
    client or (``kind="raw"``) :class:`RawModbusClient`."""
    from pymodbus.client import ModbusTcpClient

    results: list[list[float]] = [[] for _ in range(clients)]
    errors = [0] * clients
    late = [0] * clients
    start = time.perf_counter() + max(0.2, start_unix - time.time())

    def worker(i: int) -> None:
        if kind == "raw":
            c = RawModbusClient("127.0.0.1", port)
        else:
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
                if kind == "raw":
                    ok = c.read_holding(number - 40001, count, 1)
                else:
                    ok = not c.read_holding_registers(number - 40001, count=count, device_id=1).isError()
                results[i].append(time.perf_counter() - t0)
                if not ok:
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


OPCUA_ITEMS = ("ActualValues.Position", "ActualValues.Velocity", "ActualValues.FollowingError",
               "ActualValues.Current", "ActualValues.Torque", "ActualValues.MotorTemperature", "State.Statusword",
               "State.CiA402State", "State.DriveTime", "Faults.ErrorCode")
OPCUA_PUBLISH_MS = 100.0


def opcua_count(port: int, out: str) -> None:
    """An asyncua subscriber of :data:`OPCUA_ITEMS` (every axis) counting data changes until SIGTERM."""
    import asyncio

    from asyncua import Client, ua

    count = {"changes": 0, "t_first": None, "t_last": None, "items": 0}
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())

    class Handler:
        def datachange_notification(self, node, val, data):
            count["changes"] += 1
            count["t_last"] = time.time()
            count["t_first"] = count["t_first"] or count["t_last"]

    async def run() -> None:
        async with Client(f"opc.tcp://127.0.0.1:{port}/virtualaxis", timeout=30) as c:
            idx = await c.get_namespace_index("urn:virtualaxis:opcua")
            axes = await (await c.nodes.objects.get_child(f"{idx}:VirtualAxis")).get_children()
            nodes = [c.get_node(ua.NodeId(f"VirtualAxis.{(await a.read_browse_name()).Name}.{item}", idx))
                     for a in axes for item in OPCUA_ITEMS]
            sub = await c.create_subscription(OPCUA_PUBLISH_MS, Handler())
            await sub.subscribe_data_change(nodes)
            count["items"] = len(nodes)
            Path(out + ".ready").write_text("1")
            while not stop.is_set():
                await asyncio.sleep(0.1)

    asyncio.run(run())
    Path(out).write_text(json.dumps(count))


def telemetry_count(port: int, out: str, sparkplug: bool = False) -> None:
    """A paho subscriber counting telemetry samples until SIGTERM; writes ``{"samples", "batches"}``. With
    ``sparkplug``: DDATA messages are the batches and the Position values in them the samples (a sine move
    changes the position in every sample, so report by exception sends each)."""
    import paho.mqtt.client as mqtt

    count = {"samples": 0, "batches": 0, "t_first": None, "t_last": None}
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if sparkplug:
        from virtualaxis.services.sparkplug import device_alias
        from virtualaxis.services.sparkplug_proto import sparkplug_b_pb2

        position_alias = device_alias(0, 0)

    def on_message(client, userdata, m):
        count["batches"] += 1
        if sparkplug:
            p = sparkplug_b_pb2.Payload()
            p.ParseFromString(m.payload)
            count["samples"] += sum(1 for x in p.metrics if x.alias == position_alias)
        else:
            count["samples"] += len(json.loads(m.payload)["samples"])
        count["t_last"] = time.time()
        count["t_first"] = count["t_first"] or count["t_last"]

    topic = "spBv1.0/bench/DDATA/#" if sparkplug else "virtualaxis/+/+/telemetry"
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    c.on_connect = lambda c, u, f, rc, p: c.subscribe(topic, qos=0)
    c.on_message = on_message
    c.connect("127.0.0.1", port)
    c.loop_start()
    Path(out + ".ready").write_text("1")
    stop.wait()
    c.loop_stop()
    c.disconnect()
    Path(out).write_text(json.dumps(count))


def dummy_modbus_server(port: int) -> None:
    """Phase ``ext``: a plain pymodbus TCP server (static holding registers, no drive) on ``port`` until
    SIGTERM -- the same client load as phase ``modbus`` with nothing of it in ``serve``."""
    import asyncio
    import logging

    from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
    from pymodbus.server import ModbusTcpServer

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    block = ModbusSequentialDataBlock(1, list(range(1000)))
    context = ModbusServerContext(devices=ModbusDeviceContext(hr=block, ir=block), single=True)

    async def serve() -> None:
        server = ModbusTcpServer(context, address=("127.0.0.1", port))
        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
        await server.serve_forever(background=True)
        await stop.wait()
        await server.shutdown()

    asyncio.run(serve())


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


# ------------------------------------------------------------------------------------ hops
def hops(probe_file: Path, wire_sync: np.ndarray, user_sync: np.ndarray, tpdo: np.ndarray, node: int,
         raw: Path | None = None) -> dict:
    """Split every SYNC -> TPDO latency at serve's timestamps (module doc); percentiles per hop [us] and, for
    the slowest 1 % of the SYNCs, the mean of each hop (where the tail accrues)."""
    if not probe_file.exists():
        return {}
    p = np.load(probe_file)
    s_kernel, s_user = p["sync_kernel_s"], p["sync_user_s"]
    tx = p["tx_s"][p["tx_cob"] == 0x280 + node]
    n = len(wire_sync)
    if len(s_kernel) != n:  # pair serve's SYNCs with the master's by kernel time
        idx = np.clip(np.searchsorted(s_kernel, wire_sync - 5e-4), 0, max(len(s_kernel) - 1, 0))
        s_kernel, s_user = s_kernel[idx], s_user[idx]
    tx_lat = pair(tx, s_user)
    back = pair(tpdo, s_user + tx_lat) if len(tpdo) else np.full(n, np.nan)
    parts = {
        "master_send": wire_sync - user_sync,
        "to_serve_socket": s_kernel - wire_sync,
        "serve_rx_thread": s_user - s_kernel,
        "serve_runtime": tx_lat,
        "back_to_master": back,
    }
    total = pair(tpdo, wire_sync)
    out = {k: percentiles_us(v) for k, v in parts.items()}
    # serve's cyclic garbage collections inside the measured window (each holds every thread of serve)
    in_win = (p["gc_start_s"] >= wire_sync[0]) & (p["gc_start_s"] <= wire_sync[-1] + 0.1)
    gc_s, gc_gen, gc_t = p["gc_s"][in_win], p["gc_gen"][in_win], p["gc_start_s"][in_win]
    out["gc"] = {f"gen{g}": {"count": int(np.sum(gc_gen == g)),
                             "max_us": float(gc_s[gc_gen == g].max() * 1e6) if np.any(gc_gen == g) else 0.0,
                             "total_ms": float(gc_s[gc_gen == g].sum() * 1e3)} for g in (0, 1, 2)}
    ok = np.isfinite(total)
    if ok.sum() >= 100:
        cut = np.percentile(total[ok], 99)
        tail = ok & (total >= cut)
        out["tail_1pct_mean_us"] = {k: float(np.nanmean(v[tail]) * 1e6) for k, v in parts.items() if k != "master_send"}
        out["tail_1pct_mean_us"]["total"] = float(np.mean(total[tail]) * 1e6)
        # tail SYNCs during which serve collected garbage (a collection started between SYNC and TPDO)
        t0, t1 = wire_sync[tail], wire_sync[tail] + total[tail]
        i0, i1 = np.searchsorted(gc_t, t0 - 0.05), np.searchsorted(gc_t, t1)
        out["tail_1pct_with_gc_share"] = float(np.mean(i1 > i0))
        # do the slowest SYNCs fall on one phase of a 10 ms period (a periodic job in serve)? largest share of
        # them in one 1 ms bin of (time mod 10 ms); 0.1 = spread evenly
        phase_ms = ((wire_sync[tail] - wire_sync[0]) * 1e3) % 10.0
        out["tail_1pct_10ms_phase_max_share"] = float(np.histogram(phase_ms, bins=10, range=(0, 10))[0].max()
                                                      / max(1, tail.sum()))
    if raw is not None:
        np.savez(raw, wire_sync=wire_sync, user_sync=user_sync, tpdo=tpdo, s_kernel=s_kernel, s_user=s_user, tx=tx,
                 gc_start_s=p["gc_start_s"], gc_gen=p["gc_gen"], gc_s=p["gc_s"])
    return out


# ------------------------------------------------------------------------------------ one phase
def run_phase(phase_name: str, seconds: float, port: int, broker: Mosquitto | None, opts, tmp: Path) -> dict:
    base, _, ref = phase_name.partition("@")  # PHASE@ref: serve of --ref-src (an A/B in the same run)
    phase = base.removesuffix("-spb")
    sparkplug = opts.sparkplug or base.endswith("-spb")  # MQTT as Sparkplug B
    modbus_on = phase in ("load", "modbus", "idle", "all")
    external = phase == "ext"  # the Modbus clients poll a server that is not serve's (machine load only)
    mqtt_on = phase in ("load", "mqtt", "idle", "all")
    opcua_on = phase in ("opcua", "all")
    clients = phase != "idle"  # idle: serve's side channels on, nobody polls or subscribes
    spec = f"udp_multicast:239.74.163.3,port={port}"
    node = 1
    summary = tmp / f"serve-{port}.json"
    probe = tmp / f"probe-{port}.npz"
    args = [*CLI, "serve", "--can", spec, "--node-id", str(node), "--status-interval", "0",
            "--duration", str(seconds + 60), "--json", str(summary), "--bitrate", str(opts.bitrate),
            "--latency-probe", str(probe)]
    mb_port = free_port()
    if modbus_on:
        args += ["--modbus", f"127.0.0.1:{mb_port}"]
    if mqtt_on:
        args += ["--mqtt", f"mqtt://127.0.0.1:{broker.port}", "--machine", "bench"]
        if sparkplug:
            args += ["--sparkplug", "bench"]
    ua_port = free_port()
    if opcua_on:
        args += ["--opcua", f"127.0.0.1:{ua_port}"]
    if opts.rt_priority:
        args += ["--rt-priority", str(opts.rt_priority)]
    args += opts.serve_args
    dummy = None
    if external:
        dummy = subprocess.Popen([sys.executable, __file__, "--modbus-dummy", str(mb_port), "--load-priority",
                                  str(opts.load_priority)])
        wait_port(mb_port, 30.0)
        set_affinity(dummy.pid, opts.load_cpus)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if ref:
        env["PYTHONPATH"] = opts.ref_src
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    line = proc.stdout.readline()
    if not line.startswith("ready:"):
        proc.kill()
        raise RuntimeError(f"serve did not start: {line} {proc.stderr.read()}")
    for _ in range(int(modbus_on) + int(mqtt_on) + int(opcua_on)):
        proc.stdout.readline()  # "modbus: ..." / "mqtt: ..." (the server process runs by then)
    load_pids = children(proc.pid)  # serve's Modbus server and MQTT publisher processes: the clients' side
    for child in load_pids:
        set_priority(child, opts.load_priority)
        set_affinity(child, opts.load_cpus)
    if opts.drive_cpus is not None:  # serve: SYNC path on the drive CPUs, its other threads with the load
        for tid in os.listdir(f"/proc/{proc.pid}/task"):
            name = Path(f"/proc/{proc.pid}/task/{tid}/comm").read_text().strip()
            try:
                os.sched_setaffinity(int(tid), opts.drive_cpus if name in DRIVE_THREADS else opts.load_cpus)
            except OSError:
                pass
    if opts.drive_boost and opts.rt_priority:  # serve's SYNC path above its own service threads (experiment)
        for tid in os.listdir(f"/proc/{proc.pid}/task"):
            name = Path(f"/proc/{proc.pid}/task/{tid}/comm").read_text().strip()
            if name in DRIVE_THREADS:
                try:
                    os.sched_setscheduler(int(tid), os.SCHED_FIFO,
                                          os.sched_param(opts.rt_priority + opts.drive_boost))
                except OSError:
                    pass
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.3", port=port, hop_limit=0)
    clock = TpdoClock([0x280 + node, SYNC_COB])
    reply = SdoReply([node])
    notifier = can.Notifier(bus, [clock, reply], timeout=0.05)
    loader: list[subprocess.Popen] = []
    counter = ua_counter = None
    outs: list[str] = []
    out: dict = {"phase": phase_name, "seconds": seconds}
    load_flags = ["--load-priority", str(opts.load_priority)]
    if opts.load_cpus:
        load_flags += ["--load-cpus", ",".join(map(str, sorted(opts.load_cpus)))]
    try:
        x0 = setup_csp(bus, reply, node)
        out["overruns_before_load_start"] = sdo(bus, reply, node, 0x2110, 2)  # serve's start-up and the set-up
        if mqtt_on and clients:
            tel_out = str(tmp / f"telemetry-{port}.json")
            counter = subprocess.Popen([sys.executable, __file__, "--telemetry-count", str(broker.port), tel_out,
                                        *load_flags, *(["--sparkplug"] if sparkplug else [])])
        if opcua_on:
            ua_out = str(tmp / f"opcua-{port}.json")
            ua_counter = subprocess.Popen([sys.executable, __file__, "--opcua-count", str(ua_port), ua_out,
                                           *load_flags])
            end = time.monotonic() + 120
            while not Path(ua_out + ".ready").exists() and time.monotonic() < end and ua_counter.poll() is None:
                time.sleep(0.05)
            if not Path(ua_out + ".ready").exists():
                raise RuntimeError("the OPC UA subscriber did not start")
        if (modbus_on and clients) or external:
            # ten clients = ten processes (each its own interpreter, as separate client machines would be)
            outs = [str(tmp / f"modbus-{port}-{i}.json") for i in range(CLIENTS)]
            t_start = time.time() + 3.0  # all clients start polling together, once their imports are done
            loader = [
                subprocess.Popen([sys.executable, __file__, "--modbus-load", str(mb_port), str(seconds), o,
                                  *load_flags, "--load-start", f"{t_start + i * 1e-3:.6f}",
                                  "--modbus-client", opts.modbus_client])
                for i, o in enumerate(outs)
            ]
            time.sleep(max(0.0, t_start - time.time()) + 0.1)  # clients polling
        if counter is not None:
            end = time.monotonic() + 10
            while not Path(tel_out + ".ready").exists() and time.monotonic() < end:
                time.sleep(0.05)
            time.sleep(0.5)
        overruns0 = sdo(bus, reply, node, 0x2110, 2)  # drive cycle overruns (OD 0x2110:2) before the window
        out["overruns_during_load_start"] = overruns0 - out["overruns_before_load_start"]  # clients starting
        clock.clear()
        n_sync = int(seconds / PERIOD_S)
        st0, mst0, t0 = thread_schedstat(proc.pid), thread_schedstat(os.getpid()), time.perf_counter()
        with tqdm(total=n_sync, desc=f"phase {phase}", unit="sync", mininterval=1, leave=False) as bar:
            spin = (opts.master_spin_us * 1e-6 if opts.master_spin_us is not None
                    else (0.0 if opts.rt_priority else 3e-4))
            user_sync = sync_loop(bus, {node: x0}, PERIOD_S, n_sync, spin_s=spin, bar=bar)
        time.sleep(0.2)
        wall = time.perf_counter() - t0
        out["window_overruns"] = sdo(bus, reply, node, 0x2110, 2) - overruns0
        out["serve_threads"] = schedstat_delta(st0, thread_schedstat(proc.pid), wall)
        out["master_threads"] = schedstat_delta(mst0, thread_schedstat(os.getpid()), wall)
        tpdo = np.array(clock.times[0x280 + node])
        wire_sync = np.array(clock.times[SYNC_COB])
        if len(wire_sync) != n_sync:  # own SYNCs lost in the master's socket: fall back to the send times
            out["wire_sync_missing"] = int(n_sync - len(wire_sync))
            wire_sync = user_sync
        out["syncs"] = n_sync
        out.update(latency_stats(tpdo, wire_sync, PERIOD_S))
        out["user_reference"] = {k: v for k, v in latency_stats(tpdo, user_sync, PERIOD_S).items()
                                 if k.startswith("latency")}
        if counter is not None:
            counter.send_signal(signal.SIGTERM)
            counter.wait(timeout=60)  # (a loaded machine: its backlog of messages first)
            c = json.loads(Path(tel_out).read_text())
            span = (c["t_last"] - c["t_first"]) if c["t_first"] else 0.0
            out["telemetry_samples_per_s"] = c["samples"] / span if span > 0 else 0.0
            out["telemetry_batches"] = c["batches"]
        if ua_counter is not None:
            ua_counter.send_signal(signal.SIGTERM)
            ua_counter.wait(timeout=30)
            c = json.loads(Path(ua_out).read_text())
            span = (c["t_last"] - c["t_first"]) if c["t_first"] else 0.0
            out["opcua_changes_per_s"] = c["changes"] / span if span > 0 else 0.0
            out["opcua_items"] = c["items"]
        if loader:
            for lp in loader:
                lp.wait(timeout=seconds + 60)
            out["modbus"] = modbus_summary(outs, seconds)
    finally:
        for lp in [*loader, *([counter] if counter else []), *([ua_counter] if ua_counter else [])]:
            if lp.poll() is None:
                lp.kill()
        if dummy is not None:
            dummy.terminate()
            dummy.wait(timeout=10)
        notifier.stop()
        bus.shutdown()
        proc.send_signal(signal.SIGTERM)  # (SIGINT is ignored by a process started in the background)
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
    if "syncs" in out:
        raw = Path(opts.raw) / f"{len(list(Path(opts.raw).glob('*.npz'))):02d}-{phase}.npz" if opts.raw else None
        out["hops"] = hops(probe, wire_sync, user_sync, tpdo, node, raw)
    if summary.exists():
        s = json.loads(summary.read_text())
        out["drive_overruns"] = s["runtime"]["overruns"]  # the whole life of serve (start-up included)
        out["drive_max_late_ms"] = s["runtime"]["max_late_ms"]
        if "mqtt" in s:
            out["mqtt"] = next(iter(s["mqtt"].values()))
        if "opcua" in s:
            out["opcua"] = s["opcua"]
    else:
        out["drive_overruns"] = None
    return out


def _cpus(text: str) -> set[int]:
    return {int(c) for c in text.split(",") if c != ""}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=20.0, help="per phase")
    ap.add_argument("--rounds", type=int, default=2, help="passes over --phases")
    ap.add_argument("--phases", default="off,load",
                    help="comma list of off, load, modbus, mqtt, ext, idle, opcua, all, and load-spb, mqtt-spb, "
                         "idle-spb (the MQTT side as Sparkplug B)")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of serve and of the master")
    ap.add_argument("--load-priority", type=int, default=0,
                    help="SCHED_FIFO priority of the load side (Modbus clients, serve's Modbus server process, "
                    "mosquitto, the MQTT subscriber); 0 (default): normal priority")
    ap.add_argument("--pin", default=None, metavar="DRIVE_CPUS:LOAD_CPUS",
                    help="e.g. 1:0 -- serve's runtime + CAN receive threads on DRIVE_CPUS, the rest of the run "
                    "(serve's side-channel threads and processes, clients, broker, the master) on LOAD_CPUS")
    ap.add_argument("--master-spin-us", type=float, default=None,
                    help="the master spins this long before each SYNC instead of sleeping (default: 0 under "
                    "--rt-priority, where the kernel wakes a FIFO thread in time; 300 otherwise)")
    ap.add_argument("--bitrate", type=int, default=0, help="serve --bitrate (0: no CAN timing emulation)")
    ap.add_argument("--serve-arg", action="append", default=[], dest="serve_args",
                    help="extra argument for serve (repeatable), e.g. --serve-arg=--telemetry-rate=100")
    ap.add_argument("--drive-boost", type=int, default=0, metavar="K",
                    help="with --rt-priority N: serve's runtime and CAN receive threads at SCHED_FIFO N + K, above "
                    "serve's service threads (which stay at N) -- an experiment on the side channels' tail; it made "
                    "the tail 100x worse (the GIL inversion serve avoids by running all its threads at N), "
                    "BENCHMARKS.md")
    ap.add_argument("--modbus-client", choices=("pymodbus", "raw"), default="pymodbus",
                    help="the ten load clients: pymodbus' client (default) or a lean struct-packed FC03 client "
                    "(raw), whose own CPU on this host (the clients of a real drive run on other machines) is a "
                    "fraction of pymodbus'")
    ap.add_argument("--sparkplug", action="store_true",
                    help="MQTT as Sparkplug B (serve --sparkplug bench); the subscriber counts DDATA Position values")
    ap.add_argument("--ref-src", default=None, metavar="DIR",
                    help="the src folder of another virtualaxis (e.g. a checkout of the main branch): a phase "
                    "PHASE@ref (e.g. opcua@ref) runs that serve, for an A/B in the same run")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "bench_side_channels.json"))
    ap.add_argument("--raw", default=None, metavar="DIR", help="also save every phase's timestamps (.npz) in DIR")
    ap.add_argument("--load-start", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--load-cpus", default="", help=argparse.SUPPRESS)
    ap.add_argument("--modbus-load", nargs=3, metavar=("PORT", "SECONDS", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--telemetry-count", nargs=2, metavar=("PORT", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--opcua-count", nargs=2, metavar=("PORT", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--modbus-dummy", type=int, metavar="PORT", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.modbus_dummy:
        _become_load(args.load_priority, None)
        dummy_modbus_server(args.modbus_dummy)
        return 0
    if args.modbus_load or args.telemetry_count or args.opcua_count:
        _become_load(args.load_priority, _cpus(args.load_cpus) or None)
        if args.opcua_count:
            opcua_count(int(args.opcua_count[0]), args.opcua_count[1])
        elif args.modbus_load:
            modbus_load(int(args.modbus_load[0]), 1, 100.0, float(args.modbus_load[1]), args.modbus_load[2],
                        args.load_start, args.modbus_client)
        else:
            telemetry_count(int(args.telemetry_count[0]), args.telemetry_count[1], args.sparkplug)
        return 0
    phases = [p.strip() for p in args.phases.split(",") if p.strip()]
    known = ("off", "load", "modbus", "mqtt", "ext", "idle", "opcua", "all", "load-spb", "mqtt-spb", "idle-spb")
    bad = [p for p in phases if p.partition("@")[0] not in known or p.partition("@")[2] not in ("", "ref")]
    if any(p.endswith("@ref") for p in phases) and not args.ref_src:
        ap.error("--phases: a PHASE@ref phase needs --ref-src DIR")
    if bad:
        ap.error(f"--phases: unknown phase(s) {bad} ({', '.join(known)}; -spb: MQTT as Sparkplug B)")
    args.drive_cpus = args.load_cpus = None
    if args.pin:
        d, _, lo = args.pin.partition(":")
        args.drive_cpus, args.load_cpus = _cpus(d), _cpus(lo)
        os.sched_setaffinity(0, args.load_cpus)  # the master is another machine of the rig: not on the drive's
    if args.rt_priority:  # the master at the drive's priority: it measures the drive, not its own starvation
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
    results = []
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        broker = Mosquitto(tmp)
        set_priority(broker.proc.pid, args.load_priority)
        set_affinity(broker.proc.pid, args.load_cpus)
        try:
            for r in range(args.rounds):
                for i, phase in enumerate(phases):
                    port = 46000 + os.getpid() % 400 + len(phases) * r + i
                    results.append(run_phase(phase, args.seconds, port, broker, args, tmp))
        finally:
            broker.stop()
    machine = machine_info()
    machine["load_average_at_start"] = load0
    print(f"\nmachine: {machine['nproc']} cores, {machine['cpu']}, Python {machine['python']}, "
          f"load average {load0[0]:.2f} at start, {machine['load_average_at_end'][0]:.2f} at end")
    print(f"{'phase':>6} {'p50 us':>7} {'p99 us':>7} {'p99.9':>7} {'max us':>8} {'missed':>6} {'late':>5} "
          f"{'overrun':>7} {'MB p50':>7} {'MB p99':>7} {'polls/s':>7} {'tele/s':>6} {'ua/s':>5}")
    for r in results:
        mb = r.get("modbus", {})
        print(f"{r['phase']:>6} {r['latency_us_p50']:>7.0f} {r['latency_us_p99']:>7.0f} {r['latency_us_p999']:>7.0f} "
              f"{r['latency_us_max']:>8.0f} {r['missed_cycles']:>6} {r['late_tpdos']:>5} "
              f"{r.get('window_overruns', '?'):>7} "
              f"{mb.get('response_us_p50', float('nan')):>7.0f} {mb.get('response_us_p99', float('nan')):>7.0f} "
              f"{mb.get('polls_per_s', 0):>7.0f} {r.get('telemetry_samples_per_s', 0):>6.0f} "
              f"{r.get('opcua_changes_per_s', 0):>5.0f}")
    print("\nhops [us] p50 / p99 / max; tail = mean over the slowest 1 % of SYNCs; serve's threads: CPU % / "
          "run-queue wait % of the phase")
    for r in results:
        h = r.get("hops", {})
        cols = []
        for k in ("serve_rx_thread", "serve_runtime", "back_to_master", "master_send"):
            v = h.get(k, {})
            cols.append(f"{k} {v.get('p50', float('nan')):.0f}/{v.get('p99', float('nan')):.0f}/"
                        f"{v.get('max', float('nan')):.0f}")
        tail = h.get("tail_1pct_mean_us", {})
        th = r.get("serve_threads", {})
        thr = " ".join(f"{n} {v['cpu_share'] * 100:.0f}/{v['runqueue_wait_share'] * 100:.1f}"
                       for n, v in sorted(th.items()) if v["cpu_share"] > 0.005 or v["runqueue_wait_share"] > 0.001)
        print(f"{r['phase']:>6} " + "; ".join(cols))
        print(f"{'':>6} tail: " + ", ".join(f"{k} {v:.0f}" for k, v in tail.items())
              + f" (with a GC: {h.get('tail_1pct_with_gc_share', float('nan')) * 100:.0f} %, in one 1 ms bin of "
              f"10 ms: {h.get('tail_1pct_10ms_phase_max_share', float('nan')) * 100:.0f} %) | threads: {thr}")
        g = h.get("gc", {})
        print(f"{'':>6} serve GC: " + ", ".join(f"{k} {v['count']}x max {v['max_us']:.0f} us" for k, v in g.items()))
    summary = {}
    for ph in phases:
        rs = [r for r in results if r["phase"] == ph]
        summary[ph] = {"p99_us_median": float(np.median([r["latency_us_p99"] for r in rs])),
                       "p50_us_median": float(np.median([r["latency_us_p50"] for r in rs])),
                       "missed": sum(r["missed_cycles"] for r in rs)}
    if "off" in summary:
        for ph in summary:
            summary[ph]["p99_shift_vs_off_us"] = summary[ph]["p99_us_median"] - summary["off"]["p99_us_median"]
    print("\n" + "; ".join(f"{ph}: p99 {s['p99_us_median']:.0f} us"
                           + (f" ({s['p99_shift_vs_off_us']:+.0f})" if "p99_shift_vs_off_us" in s else "")
                           + f", missed {s['missed']}" for ph, s in summary.items()))
    args_out = {k: (sorted(v) if isinstance(v, set) else v) for k, v in vars(args).items()}
    Path(args.json).write_text(json.dumps({"machine": machine, "args": args_out, "summary": summary,
                                           "results": results}, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
