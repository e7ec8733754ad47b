"""A minimal poll loop around a CanopenSlave, for tests and for running a bare CiA 301 node in a process.

This is NOT the drive runtime (pacing, lockstep and the CiA 402 application live in
``virtualaxis.runtime`` / ``virtualaxis.drive``); it only does what the runtime contract says a caller does:
call ``poll(now)`` continuously and, for every SYNC counter it returns, let the application update its
values and then call ``on_sync(counter, now)``.

    python -m virtualaxis.canopen_slave.testing --interface udp_multicast --channel 239.74.163.9 \
        --port 43999 --node-id 5 --seconds 30
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can

from virtualaxis.canopen_slave.app import BaseApplication
from virtualaxis.canopen_slave.slave import CanopenSlave
from virtualaxis.resources import project_file

EDS_PATH = project_file("eds/virtualaxis.eds")   # = DEFAULT_EDS_PATH


def wait_until(predicate, timeout_s: float = 2.0, poll_s: float = 0.005) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` has passed; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return predicate()


class SlaveRunner:
    """Runs ``poll`` / ``on_sync`` of one slave in a background thread every ``period_s``."""

    def __init__(self, slave: CanopenSlave, period_s: float = 0.0005,
                 on_cycle: Callable[[CanopenSlave, int, float], None] | None = None):
        self.slave = slave
        self.period_s = period_s
        self.on_cycle = on_cycle           # called for each SYNC before on_sync (the "application cycle")
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"slave-{slave.node_id}", daemon=True)
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def start(self) -> SlaveRunner:
        with self._lock:
            self.slave.boot(self.now())
        self._thread.start()
        return self

    def call(self, fn: Callable[..., object], *args):
        """Run ``fn(*args)`` under the loop's lock (the slave is single-threaded by contract)."""
        with self._lock:
            return fn(*args)

    def _run(self) -> None:
        slave = self.slave
        while not self._stop.is_set():
            with self._lock:
                now = self.now()
                for counter in slave.poll(now):
                    if self.on_cycle is not None:
                        self.on_cycle(slave, counter, now)
                    slave.on_sync(counter, self.now())
            time.sleep(self.period_s)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="run a bare CiA 301 node (test application: none)")
    parser.add_argument("--interface", default="udp_multicast")
    parser.add_argument("--channel", required=True)
    parser.add_argument("--port", type=int, default=43113)
    parser.add_argument("--node-id", type=int, required=True)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--eds", default=str(EDS_PATH))
    parser.add_argument("--period-us", type=float, default=500.0, help="poll period (0 = spin)")
    parser.add_argument("--counting-position", action="store_true",
                        help="increment 0x6064 at every SYNC (so TPDOs carry changing data)")
    args = parser.parse_args(argv)
    kwargs: dict[str, object] = {}
    if args.interface == "udp_multicast":
        kwargs = {"port": args.port, "hop_limit": 0}
    bus = can.Bus(interface=args.interface, channel=args.channel, **kwargs)
    slave = CanopenSlave(bus, args.node_id, args.eds)

    def count(s: CanopenSlave, _counter: int, _now: float) -> None:
        s.write(0x6064, 0, (s.read(0x6064) + 1) & 0x7FFFFFFF)

    runner = SlaveRunner(slave, period_s=args.period_us * 1e-6,
                         on_cycle=count if args.counting_position else None)
    notifier = can.Notifier(bus, [slave.listener()], timeout=0.01)
    runner.start()
    print("ready", flush=True)
    try:
        deadline = time.monotonic() + args.seconds
        while time.monotonic() < deadline:
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        runner.stop()
        notifier.stop()
        bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())


class Sniffer(can.Listener):
    """Records every frame seen on a bus (a third bus on the same virtual channel) with its timestamp."""

    def __init__(self):
        self.frames: list[tuple[float, int, bytes, bool]] = []
        self._cond = threading.Condition()

    def on_message_received(self, msg: can.Message) -> None:
        with self._cond:
            # msg.timestamp: the send time on a virtual bus (no receive-thread jitter in gaps)
            self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data), msg.is_remote_frame))
            self._cond.notify_all()

    def clear(self) -> None:
        with self._cond:
            self.frames.clear()

    def of(self, cob_id: int) -> list[tuple[float, bytes]]:
        """(time, data) of the data frames (not RTRs) seen on cob_id."""
        with self._cond:
            return [(t, d) for t, c, d, r in self.frames if c == cob_id and not r]

    def wait_for(self, cob_id: int, count: int = 1, timeout_s: float = 2.0,
                 match: Callable[[bytes], bool] | None = None) -> list[tuple[float, bytes]]:
        """Wait until ``count`` frames on cob_id (matching ``match``) were seen; returns them."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                got = [(t, d) for t, c, d, r in self.frames
                       if c == cob_id and not r and (match is None or match(d))]
                remaining = deadline - time.monotonic()
                if len(got) >= count or remaining <= 0:
                    return got
                self._cond.wait(remaining)


class MasterRig:
    """A slave on a python-can ``virtual`` channel with a real ``canopen`` master (Network + RemoteNode)
    and a sniffer on two other buses of the same channel. Use as a context manager."""

    def __init__(self, node_id: int = 5, app=None, store_path: str | Path | None = None,
                 eds_path: str | Path = EDS_PATH, period_s: float = 0.0005,
                 on_cycle: Callable[[CanopenSlave, int, float], None] | None = None):
        import uuid

        import canopen

        self.channel = f"cia301-{uuid.uuid4().hex}"
        self.slave_bus = can.Bus(interface="virtual", channel=self.channel)
        self.master_bus = can.Bus(interface="virtual", channel=self.channel)
        self.sniff_bus = can.Bus(interface="virtual", channel=self.channel)
        self.sniffer = Sniffer()
        self.sniff_notifier = can.Notifier(self.sniff_bus, [self.sniffer], timeout=0.01)
        self.slave = CanopenSlave(self.slave_bus, node_id, eds_path, app=app, store_path=store_path)
        self.slave_notifier = can.Notifier(self.slave_bus, [self.slave.listener()], timeout=0.01)
        self.network = canopen.Network(self.master_bus)
        self.network.NOTIFIER_CYCLE = 0.01          # fast shutdown of the master's notifier
        self.network.connect()
        self.node = canopen.RemoteNode(node_id, str(eds_path))
        self.node.sdo.RESPONSE_TIMEOUT = 2.0  # a loaded CI machine answered later than 0.5 s (seen once)
        self.network.add_node(self.node)
        self.runner = SlaveRunner(self.slave, period_s=period_s, on_cycle=on_cycle)

    def __enter__(self) -> MasterRig:
        self.runner.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def send(self, cob_id: int, data: bytes = b"", remote: bool = False) -> None:
        """Send a raw frame from the master's bus."""
        self.master_bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False,
                                         is_remote_frame=remote, dlc=len(data) if not remote else 1))

    def nmt(self, command: int, node_id: int | None = None) -> None:
        self.send(0x000, bytes((command, self.slave.node_id if node_id is None else node_id)))

    def close(self) -> None:
        self.runner.stop()
        try:
            self.network.disconnect()
        except Exception:  # noqa: BLE001 - best effort teardown
            pass
        self.slave_notifier.stop()
        self.sniff_notifier.stop()
        for bus in (self.slave_bus, self.sniff_bus):
            bus.shutdown()


class RecordingApp(BaseApplication):
    """A test-only device application: records every hook call and refuses what ``refuse`` says.

    ``refuse[(index, sub)] = code`` makes validate_write raise SdoAbort(code); ``explode`` holds
    (index, sub) pairs whose validate_write raises RuntimeError (an application bug). Modes of operation
    (0x6060) are checked against 0x6502 like a CiA 402 drive does.
    """

    def __init__(self):
        from virtualaxis.canopen_slave.errors import SdoAbort

        self._abort = SdoAbort
        self.slave: CanopenSlave | None = None
        self.refuse: dict[tuple[int, int], int] = {}
        self.explode: set[tuple[int, int]] = set()
        self.writes: list[tuple[int, int, object]] = []
        self.reads: list[tuple[int, int]] = []
        self.states: list[int] = []
        self.errors: list[tuple[str, int]] = []
        self.resets: list[bool] = []

    def validate_write(self, index: int, sub: int, value) -> None:
        if (index, sub) in self.explode:
            raise RuntimeError("application bug")
        if (index, sub) in self.refuse:
            raise self._abort(self.refuse[(index, sub)])
        if index == 0x6060 and self.slave is not None and value > 0:
            if not self.slave.read(0x6502) >> (value - 1) & 1:
                raise self._abort(0x06090030, f"mode {value} not supported")

    def after_write(self, index: int, sub: int, value) -> None:
        self.writes.append((index, sub, value))
        if index == 0x6060 and self.slave is not None:
            self.slave.write(0x6061, 0, value)

    def before_read(self, index: int, sub: int) -> None:
        self.reads.append((index, sub))

    def on_nmt_state(self, state) -> None:
        self.states.append(int(state))

    def on_communication_error(self, kind: str, detail: int) -> None:
        self.errors.append((kind, detail))

    def on_reset(self, application: bool) -> None:
        self.resets.append(application)
