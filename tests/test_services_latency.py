"""What keeps the side channels out of the drive's way, checked through real parts:

- the shared-memory telemetry ring between serve's sampler and the MQTT publisher process: samples in order,
  samples overwritten before the publisher took them counted as lost (taken and dropped), the publisher's
  counters and last error read back consistently;
- the cycle gate: a side-channel job waits for the next PDO a real (virtual) bus sent, not for SDO traffic,
  and runs on its timeout when no PDO comes;
- ``virtualaxis serve --latency-probe`` with a side channel on, driven by a real ``canopen`` master over
  ``udp_multicast`` (hop_limit 0) sending SYNC at 1 ms: one SYNC receive record per SYNC (kernel timestamp <=
  receive-thread timestamp <= the TPDO's send timestamp), the Modbus image job gated on the PDOs, the
  service threads named.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
from served_drive import ROOT, served

from virtualaxis.services.cycle_gate import CycleGate, GateBus
from virtualaxis.services.mqtt import (
    _SLOT,
    _SLOTS_AT,
    BLOCK_BYTES,
    RING_SLOTS,
    SampleBuffer,
    TelemetryRing,
    project_pending,
)

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile


def test_telemetry_ring_order_overwrite_and_counters():
    ring = TelemetryRing(memoryview(bytearray(TelemetryRing.size(2))), 2)
    for k in range(5):
        ring.write(1, (k * 1e-3, k * 1.0, 0.0, 0.0, 0.0, 0.0))
    samples, nxt, lost = ring.read(1, 0)
    assert [s[0] for s in samples] == list(range(5)) and nxt == 5 and lost == 0
    assert samples[3][2] == 3.0
    assert ring.read(0, 0) == ([], 0, 0)  # the other axis' block is untouched
    # the publisher stalled: RING_SLOTS + 7 more samples written, the 7 oldest unread ones are overwritten
    for k in range(5, 5 + RING_SLOTS + 7):
        ring.write(1, (k * 1e-3, float(k), 0.0, 0.0, 0.0, 0.0))
    samples, nxt, lost = ring.read(1, 5)
    assert lost == 7 and nxt == 5 + RING_SLOTS + 7
    assert [s[0] for s in samples] == list(range(12, 5 + RING_SLOTS + 7))
    # a slot whose sequence is not the expected one (overwritten while read) is lost, never published torn
    w = nxt
    ring.write(1, (0.0, 1.0, 0.0, 0.0, 0.0, 0.0))
    slot_at = 1 * BLOCK_BYTES + _SLOTS_AT + (w % RING_SLOTS) * _SLOT.size
    _SLOT.pack_into(ring.buf, slot_at, w + RING_SLOTS, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    samples, nxt, lost = ring.read(1, w)
    assert samples == [] and lost == 1 and nxt == w + 1
    # lost samples count as taken and dropped in the publisher's buffer
    buf = SampleBuffer(capacity=10)
    buf.add({"seq": 0})
    buf.lose(3)
    assert buf.counters() == {"samples_taken": 4, "samples_published": 0, "samples_dropped": 3,
                              "samples_buffered": 1}
    # the publisher's counters and last error come back as written (the error cut to its field)
    ring.export(0, {"samples_taken": 11, "connects": 2, "connected": 1}, "x" * 1000)
    counters, err = ring.counters(0)
    assert counters["samples_taken"] == 11 and counters["connects"] == 2 and counters["connected"] == 1
    assert counters["samples_dropped"] == 0 and err == "x" * 254
    ring.set_sampler_late(0, 4)
    assert ring.sampler_late(0) == 4 and ring.sampler_late(1) == 0
    # serve's view before the publisher drained (still starting): the written samples counted as the next
    # drain will count them -- the oldest beyond the buffer dropped, taken = published + dropped + buffered
    c = dict.fromkeys(["samples_taken", "samples_published", "samples_dropped", "samples_buffered", "ring_next"], 0)
    assert project_pending(c, 100, 60) == c | {"samples_taken": 100, "samples_dropped": 40, "samples_buffered": 60}
    c |= {"samples_taken": 50, "samples_published": 30, "samples_buffered": 20, "ring_next": 50}
    assert project_pending(c, 50, 60) == c  # nothing pending
    p = project_pending(c, 50 + RING_SLOTS + 5, 10_000)  # the ring was lapped by 5
    assert p["samples_dropped"] == 5 and p["samples_buffered"] == 20 + RING_SLOTS
    assert p["samples_taken"] == p["samples_published"] + p["samples_dropped"] + p["samples_buffered"]


def test_cycle_gate_waits_for_a_pdo_on_a_real_bus():
    channel = f"va-gate-{os.getpid()}-{time.monotonic_ns()}"
    gate = CycleGate()
    drive_side = GateBus(can.Bus(interface="virtual", channel=channel), gate)
    master = can.Bus(interface="virtual", channel=channel)
    try:
        # no PDO at all: the job runs on its timeout
        t0 = time.perf_counter()
        assert gate.wait_next(timeout_s=0.05) is False
        assert time.perf_counter() - t0 >= 0.045

        def traffic():
            time.sleep(0.05)
            drive_side.send(can.Message(arbitration_id=0x581, data=bytes(8), is_extended_id=False))  # SDO: no
            time.sleep(0.1)
            for cob in (0x181, 0x281):  # the TPDOs of one SYNC, back to back
                drive_side.send(can.Message(arbitration_id=cob, data=bytes(6), is_extended_id=False))

        th = threading.Thread(target=traffic)
        t0 = time.perf_counter()
        th.start()
        assert gate.wait_next(timeout_s=2.0) is True
        waited = time.perf_counter() - t0
        th.join()
        assert 0.14 <= waited < 1.0, waited  # after the PDOs, not after the SDO response
        assert gate.stats() == {"pdos_marked": 2, "job_waits": 2, "job_waits_timed_out": 1}
        got = [master.recv(1.0).arbitration_id for _ in range(3)]
        assert got == [0x581, 0x181, 0x281]  # everything passes through unchanged
    finally:
        drive_side.shutdown()
        master.shutdown()


@pytest.mark.timeout(120)
def test_serve_latency_probe_with_a_real_master(tmp_path):
    probe = tmp_path / "probe.npz"
    summary = tmp_path / "serve.json"
    n_sync = 300
    with served("--node-id", "3", "--bitrate", "0", "--modbus", "127.0.0.1:0", "--latency-probe", str(probe),
                "--json", str(summary)) as srv:
        names = {Path(f"/proc/{srv.proc.pid}/task/{t}/comm").read_text().strip()
                 for t in os.listdir(f"/proc/{srv.proc.pid}/task")}
        assert {"runtime", "can-rx", "modbus-image"} <= names, names
        net = canopen.Network()
        net.connect(**srv.bus_kwargs())
        try:
            node = canopen.RemoteNode(3, str(Path(ROOT) / "eds" / "virtualaxis.eds"))
            net.add_node(node)
            node.sdo[0x1801][2].raw = 1  # TPDO2 on every SYNC
            node.nmt.state = "OPERATIONAL"
            time.sleep(0.1)
            tpdos: list[float] = []
            net.subscribe(0x283, lambda cob, data, ts: tpdos.append(ts))
            for _ in range(n_sync):
                net.sync.transmit()
                time.sleep(1e-3)
            time.sleep(0.2)
        finally:
            net.disconnect()
        assert srv.stop() == 0, srv.stderr[-2000:]
    p = np.load(probe)
    k, u, tx, cob = p["sync_kernel_s"], p["sync_user_s"], p["tx_s"], p["tx_cob"]
    assert len(k) == len(u) == n_sync
    assert np.all(k <= u) and np.all(u - k < 1.0)  # the kernel had it first, the receive thread soon after
    tx2 = tx[cob == 0x283]
    assert len(tx2) == n_sync == len(tpdos)  # one TPDO2 per SYNC, each sent after its SYNC was received
    assert np.all(tx2 >= u) and np.all(tx2[:-1] < u[1:] + 1.0)
    gate = json.loads(summary.read_text())["cycle_gate"]
    assert gate["pdos_marked"] >= n_sync
    # the image job (every 10 ms) found the PDO gap while the SYNCs ran, and ran on its timeout otherwise
    assert gate["job_waits"] > 20 and gate["job_waits"] - gate["job_waits_timed_out"] >= 10
