"""Test rig for the CiA 402 drive tests: drives served by the real runtime and CiA 301 stack on a python-can
``virtual`` bus, driven by the ``canopen`` package's master (``BaseNode402``) on the same channel.

Imported by tests/test_cia402_*.py, test_drive_*.py and test_runtime_*.py; its own tests check the rig.
"""

from __future__ import annotations

import functools
import itertools
import os
import threading
import time

import canopen
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.runtime import AxisNode, Runtime, open_bus
from virtualaxis.runtime.axes import DEFAULT_CONFIG
from virtualaxis.sim import AxisSimulator

_channels = itertools.count()


@functools.lru_cache(maxsize=1)
def seed_config():
    return load_axis_config(DEFAULT_CONFIG)


@functools.lru_cache(maxsize=1)
def seed_discrete():
    """The discretised mechanics of the seed axis, shared by all rigs (building it takes ~0.7 s)."""
    return AxisSimulator(seed_config()).dm


class EmcyLog:
    """EMCY frames seen by the master (COB-ID, code, error register)."""

    def __init__(self, network: canopen.Network, cob_ids: list[int]):
        self.frames: list[tuple[int, int, int, bytes]] = []
        self._cond = threading.Condition()
        for cob in cob_ids:
            network.subscribe(cob, self._on_frame)

    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._cond:
            code = int.from_bytes(data[0:2], "little")
            self.frames.append((can_id, code, data[2], bytes(data[3:8])))
            self._cond.notify_all()

    def codes(self) -> list[int]:
        with self._cond:
            return [f[1] for f in self.frames]

    def wait_for(self, code: int, timeout: float = 2.0) -> tuple[int, int, int, bytes]:
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                for f in self.frames:
                    if f[1] == code:
                        return f
                left = end - time.monotonic()
                if left <= 0:
                    raise AssertionError(f"no EMCY 0x{code:04X} (seen {[hex(c) for c in self.codes()]})")
                self._cond.wait(left)


class Rig:
    """``nodes``: node id -> (config, initial position [m]). ``lockstep``: the plants advance on SYNC only."""

    def __init__(self, nodes: dict | None = None, *, lockstep: bool = True, heartbeat_ms: int = 50):
        cfg = seed_config()
        nodes = nodes or {1: (cfg, 0.0)}
        self.channel = f"va-rig-{os.getpid()}-{next(_channels)}"
        self.bus = open_bus(f"virtual:{self.channel}")
        self.axes = {
            nid: AxisNode(
                self.bus,
                nid,
                c,
                name=f"axis{nid}",
                initial_position_m=x0,
                discrete=seed_discrete() if c is cfg else None,
                allow_fault_injection=True,  # the rig's tests inject faults by 0x2010
            )
            for nid, (c, x0) in nodes.items()
        }
        self.runtime = Runtime(self.bus, list(self.axes.values()), lockstep=lockstep)
        self.net = canopen.Network()
        self.net.connect(interface="virtual", channel=self.channel)
        self.emcy = EmcyLog(self.net, [0x80 + nid for nid in nodes])
        self.nodes: dict[int, canopen.BaseNode402] = {}
        for nid in nodes:
            node = canopen.BaseNode402(nid, str(DEFAULT_EDS))
            node.sdo.RESPONSE_TIMEOUT = 2.0  # a loaded CI machine may answer later than the default 0.3 s
            self.net.add_node(node)
            self.nodes[nid] = node
        self.runtime.start()
        for node in self.nodes.values():
            node.sdo[0x1017].raw = heartbeat_ms
            node.nmt.wait_for_heartbeat(5.0)

    @property
    def node(self) -> canopen.BaseNode402:
        return next(iter(self.nodes.values()))

    @property
    def drive(self):
        return next(iter(self.axes.values())).drive

    def sync(self, n: int = 1, timeout: float = 5.0) -> None:
        """Send ``n`` SYNC frames, each after the previous one has been handled by the runtime."""
        stats = self.runtime.stats
        for _ in range(n):
            target = stats.syncs + 1
            self.net.sync.transmit()
            end = time.monotonic() + timeout
            while stats.syncs < target:
                if time.monotonic() > end:
                    raise AssertionError("the runtime did not handle the SYNC")
                time.sleep(20e-6)
        time.sleep(0.001)  # let the master's receive thread take the TPDOs of the last SYNC

    def wait(self, predicate, timeout: float = 2.0, sync: bool = False):
        """Wait until ``predicate()`` is true. With ``sync``, one SYNC per check and ``timeout`` counted in drive
        time: at most ``timeout`` / 1 ms SYNCs (a busy host makes each SYNC take longer, not the axis need more of
        them; a wall-clock bound 20x that keeps a stuck runtime from hanging the test). Without, ``timeout`` s."""
        end = time.monotonic() + (timeout * 20 + 30 if sync else timeout)
        syncs = 0
        while True:
            value = predicate()
            if value:
                return value
            if time.monotonic() > end or (sync and syncs >= timeout / 1e-3):
                raise AssertionError(f"condition not reached in time ({syncs} SYNCs sent)" if sync
                                     else "condition not reached in time")
            if sync:
                self.sync(1)
                syncs += 1
            else:
                time.sleep(0.002)

    def sw(self, nid: int | None = None) -> int:
        node = self.nodes[nid] if nid else self.node
        return node.sdo[0x6041].raw

    def enable(self, nid: int | None = None) -> None:
        """shutdown, switch on, enable operation by SDO controlword."""
        node = self.nodes[nid] if nid else self.node
        for cw, expect in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
            node.sdo[0x6040].raw = cw
            assert node.sdo[0x6041].raw & 0x6F == expect

    def close(self) -> None:
        self.net.sync.stop()
        self.net.disconnect()
        self.runtime.stop()
        self.bus.shutdown()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_rig_boots_the_drive_in_switch_on_disabled(rig):
    """Checklist 1 and 5: boot, statusword 0x40 before any controlword, device type of a CiA 402 servo."""
    assert rig.node.nmt.state == "PRE-OPERATIONAL"
    assert rig.sw() & 0x4F == 0x40
    assert rig.node.sdo[0x1000].raw & 0xFFFF == 0x0192
    assert rig.node.sdo[0x6502].raw == 0x3ED


def test_rig_sync_advances_the_plant_one_cycle_per_sync(rig):
    before = rig.drive.counters["cycles"]
    rig.sync(7)
    assert rig.drive.counters["cycles"] - before == 7
