"""NMT error control: heartbeat producer (0x1017), heartbeat consumer (0x1016) and node guarding
(RTR on 0x700 + id with toggle bit, life time = 0x100C x 0x100D)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.errors import SdoAbort

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import CommErrorNode

HEARTBEAT_BASE = 0x700


class HeartbeatProducer:
    def __init__(self, slave: CommErrorNode):
        self.slave = slave
        self.next_s: float | None = None

    @property
    def period_s(self) -> float:
        return self.slave.od.value(0x1017) * 1e-3

    def restart(self, now_s: float) -> None:
        period = self.period_s
        self.next_s = now_s + period if period > 0 else None

    def poll(self, now_s: float) -> None:
        if self.next_s is not None and now_s >= self.next_s:
            self.slave.send(HEARTBEAT_BASE + self.slave.node_id, bytes((int(self.slave.nmt_state),)))
            period = self.period_s
            self.next_s = self.next_s + period
            if self.next_s <= now_s:          # far behind (e.g. the caller paused): no burst
                self.next_s = now_s + period


@dataclass
class Monitor:
    node_id: int
    timeout_s: float
    last_rx_s: float | None = None      # monitoring starts with the first heartbeat received
    lost: bool = False


class HeartbeatConsumer:
    def __init__(self, slave: CommErrorNode):
        self.slave = slave
        self.monitors: dict[int, Monitor] = {}
        self.configure()

    def configure(self) -> None:
        od = self.slave.od
        self.monitors = {}
        if 0x1016 not in od.objects:
            return
        for sub in range(1, od.value(0x1016, 0) + 1):
            node, time_ms = _split(od.value(0x1016, sub))
            if time_ms and 1 <= node <= 127 and node != self.slave.node_id:
                self.monitors[HEARTBEAT_BASE + node] = Monitor(node, time_ms * 1e-3)
        monitored = {m.node_id for m in self.monitors.values()}
        for node in self.slave.comm_error_sources(0x8130) - monitored - {0}:
            self.slave.clear_comm_error(0x8130, node)  # a producer no longer monitored is no longer lost

    def validate_write(self, _index: int, sub: int, value: int) -> None:
        node, time_ms = _split(value)
        if value >> 24:
            raise SdoAbort(ab.INVALID_VALUE, "bits 24-31 of 0x1016 entries are reserved")
        if not time_ms or not node:
            return
        od = self.slave.od
        for other in range(1, od.value(0x1016, 0) + 1):
            o_node, o_time = _split(od.value(0x1016, other))
            if other != sub and o_node == node and o_time:
                raise SdoAbort(ab.PARAMETER_INCOMPATIBLE, f"node {node} is already monitored by sub {other}")

    def after_write(self, _index: int, _sub: int) -> None:
        self.configure()
        self.slave.rebuild_dispatch()

    def on_heartbeat(self, cob: int, data: bytes, now_s: float) -> None:
        monitor = self.monitors.get(cob)
        if monitor is None:
            return
        if len(data) != 1:
            self.slave.counters["malformed_frames"] += 1
            return
        monitor.last_rx_s = now_s
        if monitor.lost:
            monitor.lost = False
            self.slave.clear_comm_error(0x8130, monitor.node_id)  # the producer is back

    def poll(self, now_s: float) -> None:
        for monitor in self.monitors.values():
            last = monitor.last_rx_s
            if last is not None and not monitor.lost and now_s - last > monitor.timeout_s:
                monitor.lost = True
                self.slave.counters["heartbeat_timeouts"] += 1
                self.slave.raise_comm_error(0x8130, monitor.node_id, bytes((monitor.node_id,)))
                self.slave.communication_error("heartbeat_lost", monitor.node_id)
                self.slave.error_behaviour()


def _split(value: int) -> tuple[int, int]:
    return (value >> 16) & 0xFF, value & 0xFFFF


class NodeGuarding:
    def __init__(self, slave: CommErrorNode):
        self.slave = slave
        self.reset()

    def reset(self) -> None:
        self.toggle = 0
        self.last_rtr_s: float | None = None
        self.lost = False

    def on_rtr(self, now_s: float) -> None:
        slave = self.slave
        if slave.od.value(0x1017) != 0:       # heartbeat producer active: node guarding not used
            return
        slave.send(HEARTBEAT_BASE + slave.node_id, bytes(((self.toggle << 7) | int(slave.nmt_state),)))
        slave.counters["node_guard_replies"] += 1
        self.toggle ^= 1
        self.last_rtr_s = now_s
        if self.lost:
            self.lost = False
            slave.clear_comm_error(0x8130, 0)  # the master guards again

    def poll(self, now_s: float) -> None:
        if self.last_rtr_s is None or self.lost:
            return
        od = self.slave.od
        life_s = od.value(0x100C) * od.value(0x100D) * 1e-3
        if life_s > 0.0 and now_s - self.last_rtr_s > life_s:
            self.lost = True
            self.slave.counters["life_guarding_events"] += 1
            self.slave.raise_comm_error(0x8130, 0)
            self.slave.communication_error("life_guarding", self.slave.node_id)
            self.slave.error_behaviour()
