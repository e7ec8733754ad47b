"""A user's controller test in CI: the contour program of contour.ngc run as CSP on two virtual axes (X = node 1,
Y = node 2) in SYNC lockstep, through a real CANopen master (RPDO2 = controlword + target position, TPDO2 =
statusword + actual position every SYNC), with the contour error held to a tolerance.

    pytest examples/gcode_contour                            # passes
    GCODE_KV_X=1.0 pytest examples/gcode_contour             # X position-loop gain Kv mistuned: fails

Settings by environment: GCODE_KV_X / GCODE_KV_Y (Kv [1000/min], default: the drive's), GCODE_TOLERANCE_UM
(default 40), GCODE_TRANSPORT (virtual | udp, default virtual), GCODE_REPORT (a JSON file for the figures).
"""

from __future__ import annotations

import json
import os
import queue
import struct
from pathlib import Path

import can
import numpy as np
import pytest
from interpolator import contour_error_mm, interpolate, parse

HERE = Path(__file__).resolve().parent
X, Y = 1, 2
UNIT_MM = 1e-3  # 1 position unit = 1 um (the drive's default 0x608F/0x6091/0x6092)
TOLERANCE_UM = float(os.environ.get("GCODE_TOLERANCE_UM", "40"))


class Tpdo2(can.Listener):
    """Actual positions from TPDO2 (0x280 + node: statusword, 0x6064) into a queue."""

    def __init__(self) -> None:
        self.q: queue.Queue = queue.Queue()

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id in (0x280 + X, 0x280 + Y) and len(msg.data) == 6:
            sw, pos = struct.unpack("<Hi", bytes(msg.data))
            self.q.put((msg.arbitration_id - 0x280, sw, pos))


def _step(axis, tpdo: Tpdo2, targets: dict[int, int], cw: int = 0x0F) -> dict[int, tuple[int, int]]:
    """One interpolation cycle: RPDO2 per axis, SYNC, then both TPDO2 answers (node -> (statusword, pos))."""
    net = axis.network
    for nid, target in targets.items():
        net.send_message(0x300 + nid, struct.pack("<Hi", cw, target))
    net.send_message(0x80, b"")
    got: dict[int, tuple[int, int]] = {}
    while len(got) < 2:
        nid, sw, pos = tpdo.q.get(timeout=5.0)
        got[nid] = (sw, pos)
    return got


@pytest.mark.virtual_axis(node_id=(X, Y), lockstep=True, transport=os.environ.get("GCODE_TRANSPORT", "virtual"))
def test_contour_within_tolerance(virtual_axis):
    blocks = parse((HERE / "contour.ngc").read_text())
    path_mm = interpolate(blocks, cycle_s=0.001)
    tpdo = Tpdo2()
    virtual_axis.network.notifier.add_listener(tpdo)
    for nid, env in ((X, "GCODE_KV_X"), (Y, "GCODE_KV_Y")):
        node = virtual_axis.nodes[nid]
        if os.environ.get(env):
            node.sdo[0x2000].raw = float(os.environ[env])  # position-loop gain Kv [1000/min] (MD32200)
        node.sdo[0x6060].raw = 8  # CSP
        node.nmt.state = "OPERATIONAL"
    # origin: where the axes are; enable with the set-point on the actual position (CSP takes it at once)
    origin = {nid: virtual_axis.nodes[nid].sdo[0x6064].raw for nid in (X, Y)}
    for cw in (0x06, 0x07, 0x0F):
        for _ in range(20):
            got = _step(virtual_axis, tpdo, origin, cw)
        assert all(sw & 0x6F == {0x06: 0x21, 0x07: 0x23, 0x0F: 0x27}[cw] for sw, _ in got.values()), got
    actual = np.empty_like(path_mm)
    for k, (x_mm, y_mm) in enumerate(path_mm):
        got = _step(virtual_axis, tpdo, {X: origin[X] + round(x_mm / UNIT_MM), Y: origin[Y] + round(y_mm / UNIT_MM)})
        for sw, _ in got.values():
            assert sw & 0x4F != 0x08, f"drive FAULT at cycle {k} (statusword 0x{sw:04X})"
        # the answer to SYNC k carries the position at the end of cycle k - 1
        actual[max(k - 1, 0)] = [(got[X][1] - origin[X]) * UNIT_MM, (got[Y][1] - origin[Y]) * UNIT_MM]
    actual[-1] = actual[-2]
    err_um = contour_error_mm(path_mm, actual) * 1e3
    worst = int(np.argmax(err_um))
    report = {"cycles": len(path_mm), "max_contour_error_um": float(err_um.max()),
              "rms_contour_error_um": float(np.sqrt(np.mean(err_um**2))), "worst_at_mm": path_mm[worst].tolist(),
              "tolerance_um": TOLERANCE_UM, "kv_x": os.environ.get("GCODE_KV_X", "default"),
              "kv_y": os.environ.get("GCODE_KV_Y", "default")}
    print(json.dumps(report))
    if os.environ.get("GCODE_REPORT"):
        Path(os.environ["GCODE_REPORT"]).write_text(json.dumps(report, indent=1))
    assert err_um.max() <= TOLERANCE_UM, (
        f"contour error {err_um.max():.1f} um > {TOLERANCE_UM:g} um at X{path_mm[worst][0]:.3f} "
        f"Y{path_mm[worst][1]:.3f} (cycle {worst})")
