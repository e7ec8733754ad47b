"""Issue #15 item 5 (defaults that fault on ordinary moves), homing onto a limit switch: with the default homing
acceleration (0x609A = 0.5 m/s^2, made for the slow return) a search at 200 mm/s toward a limit switch ran the
table 40 mm past the switch into the end stop and faulted (following error 0x8611, homing error). On the switch
and still moving into it the drive now brakes with at least the quick-stop deceleration 0x6085, its limit-switch
reaction in every other mode. Through a real ``canopen`` master (``Rig``: virtual bus, lockstep)."""

from __future__ import annotations

import time

import pytest
from test_drive_rig import Rig


@pytest.mark.parametrize("method", [17, 2])
def test_homing_onto_a_limit_switch_at_200_mm_s_with_default_accelerations(method):
    r = Rig()
    try:
        node = r.node
        node.sdo[0x6098].raw = method
        node.sdo[0x6060].raw = 6
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.01)
        r.enable()
        node.sdo[0x6099][1].raw = 200_000  # 200 mm/s search (0x607F allows 500 mm/s)
        node.sdo[0x6040].raw = 0x1F
        sw = 0
        peak_mm = 0.0
        half_mm = r.drive.cfg.axis.stroke_m / 2 * 1e3
        for _ in range(200):
            r.sync(50)
            peak_mm = max(peak_mm, abs(r.drive.state.position_actual_m) * 1e3)
            sw = r.sw()
            if sw & 0x3000 or sw & 0x6F == 0x28:
                break
        assert sw & 0x3000 == 0x1000, f"statusword 0x{sw:04X}, 0x603F 0x{node.sdo[0x603F].raw:04X}"
        assert node.sdo[0x603F].raw == 0
        assert peak_mm < half_mm + 5.0  # braked within a few mm past the switch, far from the end stop
    finally:
        r.close()
