"""Frame delivery to the slaves of one runtime: one listener per slave (every frame to every slave, as before)
against the runtime's COB-ID router (a frame only to the slaves that listen to it).

    python benchmarks/bench_canopen_routing.py

Seven bare CiA 301 slaves (nodes 1-7, OPERATIONAL) and the traffic of 1 ms of a 7-axis CSP master: seven
RPDOs and one SYNC. Prints the best of 5 x 2000 repetitions [us per millisecond of traffic]: delivery alone
and delivery + the seven slaves' ``poll``.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import can

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from virtualaxis.canopen_slave import CanopenSlave, NmtState  # noqa: E402
from virtualaxis.canopen_slave.testing import EDS_PATH  # noqa: E402
from virtualaxis.runtime.pacing import _Router  # noqa: E402


def main() -> int:
    bus = can.Bus(interface="virtual", channel="bench-routing")
    slaves = [CanopenSlave(bus, n, EDS_PATH) for n in range(1, 8)]
    for s in slaves:
        s.boot(0.0)
        s._set_state(NmtState.OPERATIONAL)
    frames = [can.Message(arbitration_id=0x300 + n, data=bytes(6), is_extended_id=False) for n in range(1, 8)]
    frames.append(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))
    wake = threading.Event()
    router = _Router(slaves, wake)

    def every_slave(poll: bool) -> None:
        for m in frames:
            for s in slaves:
                s.receive(m)
            wake.set()
        for s in slaves:
            s.poll(0.0) if poll else s._queue.clear()

    def routed(poll: bool) -> None:
        for m in frames:
            router.on_message_received(m)
        for s in slaves:
            s.poll(0.0) if poll else s._queue.clear()

    def best(fn, poll: bool) -> float:
        out = float("inf")
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(2000):
                fn(poll)
            out = min(out, (time.perf_counter() - t) / 2000)
        return out * 1e6

    try:
        for poll in (False, True):
            a, b = best(every_slave, poll), best(routed, poll)
            what = "delivery + 7 polls" if poll else "delivery"
            print(f"{what:>20}: every slave {a:6.1f} us, routed {b:6.1f} us per ms of traffic ({a / b:.2f}x)")
    finally:
        bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
