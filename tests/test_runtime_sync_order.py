"""Order of a SYNC answer with several axes on one bus.

The runtime answers a SYNC in two passes: every axis' synchronous TPDOs first (the values sampled at the SYNC
instant), then every axis' synchronous RPDOs applied. Seen by a real ``canopen`` master: a TPDO that maps an
object the same SYNC's RPDO writes (here the target position 0x607A) shows the value of the previous SYNC, and
the new value one SYNC later, for every axis; the plant still runs the new set-point in the cycle after the
SYNC (CSP follows the target as before).
"""

from __future__ import annotations

import os
import time

import canopen
import pytest
from test_drive_rig import seed_config, seed_discrete

from virtualaxis.runtime import AxisNode, Runtime, open_bus

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

EDS = os.path.join(os.path.dirname(__file__), "..", "eds", "virtualaxis.eds")
N_AXES = 3


@pytest.fixture
def three_axes():
    channel = f"va-sync-order-{os.getpid()}-{time.monotonic_ns()}"
    bus = open_bus(f"virtual:{channel}")
    cfg, disc = seed_config(), seed_discrete()
    axes = [AxisNode(bus, n, cfg, discrete=disc, name=f"A{n}") for n in range(1, N_AXES + 1)]
    rt = Runtime(bus, axes, lockstep=True)
    rt.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        yield network, axes, rt
    finally:
        network.disconnect()
        rt.stop()
        bus.shutdown()


class _Received:
    """Target position of every TPDO2 a node sent, in order (canopen's PDO callback, its receive thread)."""

    def __init__(self, nodes):
        self.values = {node.id: [] for node in nodes}
        for node in nodes:
            node.tpdo[2].add_callback(self._on_tpdo)

    def _on_tpdo(self, pdo_map) -> None:
        self.values[pdo_map.pdo_node.node.id].append(pdo_map["Target position"].raw)

    def wait(self, counts: dict[int, int], timeout_s: float = 2.0) -> None:
        end = time.monotonic() + timeout_s
        while any(len(self.values[n]) < c for n, c in counts.items()):
            assert time.monotonic() < end, f"TPDO2s received {self.values}, expected counts {counts}"
            time.sleep(0.001)


def _configure(network: canopen.Network, node_id: int) -> canopen.RemoteNode:
    """RPDO2 = controlword + target position, synchronous; TPDO2 = statusword + target position, every SYNC."""
    node = network.add_node(node_id, EDS)
    node.sdo.RESPONSE_TIMEOUT = 2.0
    node.nmt.state = "PRE-OPERATIONAL"
    node.sdo[0x1006].raw = 1000  # 1 ms communication cycle
    node.rpdo.read()
    node.tpdo.read()
    node.rpdo[2].trans_type = 1
    node.rpdo[2].save()
    tpdo = node.tpdo[2]
    tpdo.clear()
    tpdo.add_variable(0x6041)
    tpdo.add_variable(0x607A)
    tpdo.trans_type = 1
    tpdo.enabled = True
    tpdo.save()
    for n in (1, 3, 4):
        node.tpdo[n].enabled = False
        node.tpdo[n].save()
    node.nmt.state = "OPERATIONAL"
    return node


def test_tpdo_samples_before_the_same_syncs_rpdo_for_every_axis(three_axes):
    network, axes, rt = three_axes
    nodes = [_configure(network, ax.node_id) for ax in axes]
    received = _Received(nodes)
    for k in range(1, 5):
        for node in nodes:
            node.rpdo[2]["Controlword"].raw = 0
            node.rpdo[2]["Target position"].raw = 1000 * k + node.id
            node.rpdo[2].transmit()
        time.sleep(0.01)  # the RPDOs reach the slaves before the SYNC (a CAN bus keeps the order)
        network.sync.transmit()
        received.wait({node.id: k for node in nodes})
    # SYNC k's TPDO carries the target of SYNC k-1 (0 before the first RPDO), for every axis
    for node in nodes:
        assert received.values[node.id] == [0] + [1000 * k + node.id for k in range(1, 4)], received.values
    # and the drive holds the latest target once the SYNC's RPDOs are applied (in the cycle after its TPDOs
    # went out: the master may see the TPDO before the runtime thread has applied the RPDO)
    for ax, node in zip(axes, nodes, strict=True):
        end = time.monotonic() + 5.0
        while ax.drive.read_object(0x607A) != 4000 + node.id and time.monotonic() < end:
            time.sleep(0.005)
        assert ax.drive.read_object(0x607A) == 4000 + node.id
    assert rt.healthy


def test_csp_follows_each_target_in_the_cycle_after_its_sync(three_axes):
    """The two-pass answer does not delay the plant: the set-point of SYNC k is interpolated in cycle k."""
    network, axes, rt = three_axes
    nodes = [_configure(network, ax.node_id) for ax in axes]
    for node in nodes:
        node.sdo[0x6060].raw = 8
        node.sdo[0x6065].raw = 50_000
        for cw in (0x06, 0x07, 0x0F):
            node.sdo[0x6040].raw = cw
    x0 = {ax.node_id: ax.drive.read_object(0x6064) for ax in axes}
    received = _Received(nodes)
    for k in range(1, 4):
        for node in nodes:
            node.rpdo[2]["Controlword"].raw = 0x0F
            node.rpdo[2]["Target position"].raw = x0[node.id] + 5 * k
            node.rpdo[2].transmit()
        time.sleep(0.01)
        network.sync.transmit()
        received.wait({node.id: k for node in nodes})
        time.sleep(0.01)  # (the RPDOs are applied and the cycle run right after the TPDOs went out)
        with rt.lock:  # the cycle after SYNC k runs on SYNC k's target, on every axis
            for ax in axes:
                assert ax.drive._csp.interp.end == pytest.approx((x0[ax.node_id] + 5 * k) * ax.drive._u)
    assert rt.healthy
