"""SYNC -> TPDO2 latency of a bare CiA 301 node (no CiA 402 application, no plant) in another process over
udp_multicast (hop_limit 0). Master: SYNC every period; latency = TPDO2 receive - SYNC send (perf_counter,
same process). Usage: python benchmarks/bench_canopen_udp_latency.py PERIOD_US SECONDS POLL_PERIOD_US"""
import statistics
import struct
import subprocess
import sys
import threading
import time

import can

sys.setswitchinterval(5e-5)   # the receive thread must not wait for the sending loop's GIL slice

period_us, seconds, poll_us = float(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
channel, port, node = "239.74.201.77", 45877, 31
proc = subprocess.Popen([sys.executable, "-m", "virtualaxis.canopen_slave.testing", "--interface",
                         "udp_multicast", "--channel", channel, "--port", str(port), "--node-id", str(node),
                         "--seconds", str(seconds + 10), "--counting-position", "--period-us", poll_us],
                        stdout=subprocess.PIPE, text=True)
assert proc.stdout.readline().strip() == "ready"
bus = can.Bus(interface="udp_multicast", channel=channel, port=port, hop_limit=0)
recv_times = {}
stop = threading.Event()


def reader():
    while not stop.is_set():
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == 0x280 + node:
            recv_times[struct.unpack_from("<i", msg.data, 2)[0]] = time.perf_counter()


threading.Thread(target=reader, daemon=True).start()
bus.send(can.Message(arbitration_id=0, data=bytes((1, node)), is_extended_id=False))
time.sleep(0.3)
sent = []
n = int(seconds * 1e6 / period_us)
t_next = time.perf_counter()
for _ in range(n):
    t_next += period_us * 1e-6
    remaining = t_next - time.perf_counter()
    if remaining > 0:
        time.sleep(remaining)
    sent.append(time.perf_counter())
    bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
time.sleep(0.3)
stop.set()
proc.terminate()
proc.wait()
# position k (k = 1..n) is the value after the k-th SYNC's cycle
base = min(recv_times) if recv_times else 1
lat = [(recv_times[base + i] - sent[i]) * 1e6 for i in range(n) if base + i in recv_times]
lat.sort()
missed = n - len(lat)
print(f"SYNC period {period_us:.0f} us, {seconds:.0f} s, poll period {poll_us} us: n={n} missed={missed} "
      f"p50={lat[len(lat)//2]:.0f} us p99={lat[int(len(lat)*0.99)]:.0f} us max={lat[-1]:.0f} us "
      f"mean={statistics.fmean(lat):.0f} us")
bus.shutdown()
