"""Cost of CanopenSlave.poll()/on_sync() in the caller's thread (python-can virtual bus, no master thread).

Prints per-call p50/p99/max in microseconds for: idle poll, a SYNC cycle (poll with one SYNC frame queued
+ on_sync sending TPDO2 (type 1) after an application write), an RPDO cycle, and an expedited SDO upload.
"""
import statistics
import time

import can

from virtualaxis.canopen_slave import CanopenSlave
from virtualaxis.canopen_slave.testing import EDS_PATH

N = 20000


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


def report(name, xs):
    us = [x * 1e6 for x in xs]
    print(f"{name:28s} p50 {pct(us, .5):7.2f} us  p99 {pct(us, .99):7.2f} us  max {max(us):8.2f} us"
          f"  mean {statistics.fmean(us):6.2f} us  (n={len(us)})")


bus = can.Bus(interface="virtual", channel="bench-301")
sink = can.Bus(interface="virtual", channel="bench-301")   # a peer so sends are delivered somewhere
slave = CanopenSlave(bus, 1, EDS_PATH)
slave.boot(0.0)
slave.receive(can.Message(arbitration_id=0, data=b"\x01\x01", is_extended_id=False))
slave.poll(0.0)
pos = slave.entry(0x6064)
clock = time.perf_counter
idle, sync_cycle, rpdo_cycle, sdo_cycle = [], [], [], []
sync_msg = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
rpdo_msg = can.Message(arbitration_id=0x301, data=b"\x0f\x00\x10\x00\x00\x00", is_extended_id=False)
sdo_msg = can.Message(arbitration_id=0x601, data=b"\x40\x41\x60\x00\x00\x00\x00\x00", is_extended_id=False)
now = 0.0
for i in range(N):
    now += 0.001
    t0 = clock()
    slave.poll(now)
    idle.append(clock() - t0)
    slave.receive(sync_msg)
    t0 = clock()
    for counter in slave.poll(now):
        slave.write_entry(pos, i)
        slave.on_sync(counter, now)
    sync_cycle.append(clock() - t0)
    slave.receive(rpdo_msg)
    t0 = clock()
    slave.poll(now)
    rpdo_cycle.append(clock() - t0)
    slave.receive(sdo_msg)
    t0 = clock()
    slave.poll(now)
    sdo_cycle.append(clock() - t0)
    while sink.recv(0) is not None:
        pass
report("poll() idle", idle)
report("SYNC -> on_sync -> TPDO2", sync_cycle)
report("RPDO2 (6 bytes) applied", rpdo_cycle)
report("SDO expedited upload", sdo_cycle)
assert slave.counters["internal_errors"] == 0
print("tpdo_sent", slave.counters["tpdo_sent"], "rpdo_received", slave.counters["rpdo_received"])
bus.shutdown()
sink.shutdown()
