"""Issue #15 item 5 (defaults that fault on ordinary moves), homing onto a limit switch: with the default homing
acceleration (0x609A = 0.5 m/s^2, made for the slow return) a search at 200 mm/s toward a limit switch ran the
table 40 mm past the switch into the end stop and faulted (following error 0x8611, homing error). On the switch
and still moving into it the drive now brakes with at least the quick-stop deceleration 0x6085, its limit-switch
reaction in every other mode. Through a real ``canopen`` master (``Rig``: virtual bus, lockstep)."""

from __future__ import annotations

import time

import pytest
from test_drive_rig import Rig

from virtualaxis.sim.simulator import end_stops


@pytest.mark.parametrize(("method", "search_um_s"), [(17, 200_000), (2, 200_000), (18, 500_000), (1, 500_000)])
def test_homing_onto_a_limit_switch_at_up_to_500_mm_s_with_default_accelerations(method, search_um_s):
    """200 mm/s and 500 mm/s (the 0x607F default) searches; at 500 mm/s the quick-stop brakes 12.5 mm past the
    switch, which is inside the end stop's over-travel (before: the end stop was 10 mm out and it faulted
    0x8611)."""
    r = Rig()
    try:
        node = r.node
        node.sdo[0x6098].raw = method
        node.sdo[0x6060].raw = 6
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.01)
        r.enable()
        node.sdo[0x6099][1].raw = search_um_s  # search speed (0x607F allows 500 mm/s)
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
        stop_mm = end_stops(r.drive.cfg)[1] * 1e3
        assert peak_mm < stop_mm  # never touched the end stop
        if search_um_s <= 200_000:
            assert peak_mm < half_mm + 5.0  # braked within a few mm past the switch
    finally:
        r.close()
