"""Profile position change on set-point, touch probe, polarity and interpolated position mode through a real
``canopen`` master (in-process on the ``virtual`` bus, SYNC lockstep)."""

from __future__ import annotations

from test_cia402_modes import _pp_rig


def test_profile_position_change_on_setpoint_passes_the_first_target_at_its_velocity():
    """Bit 9 = 1, bit 5 = 0: the buffered second set-point starts as the first target is passed; the axis passes
    it at the first set-point's profile velocity and goes on at the second one's."""
    r = _pp_rig()
    node = r.node
    try:
        node.sdo[0x607A].raw = 20_000  # 20 mm at 0.1 m/s
        node.sdo[0x6040].raw = 0x21F
        node.sdo[0x6040].raw = 0x20F
        r.sync(5)  # moving toward the first target
        node.sdo[0x607A].raw = 40_000
        node.sdo[0x6081].raw = 50_000  # the second set-point's velocity
        node.sdo[0x6040].raw = 0x21F  # buffered: bit 12 stays set until the first target is passed
        assert r.sw() & 0x1000
        node.sdo[0x6040].raw = 0x20F
        near_first, after = [], []
        for _ in range(1200):
            r.sync(1)
            x, v = node.sdo[0x6064].raw, node.sdo[0x606C].raw
            if 17_000 <= x <= 20_000:
                near_first.append(v)
            elif 30_000 <= x <= 35_000:
                after.append(v)
            if r.sw() & 0x400:
                break
        assert near_first and min(near_first) > 90_000, near_first  # no stop at the first target
        assert after and all(abs(v - 50_000) < 3_000 for v in after), after
        assert not r.sw() & 0x1000  # both set-points taken
        assert abs(node.sdo[0x6064].raw - 40_000) <= node.sdo[0x6067].raw
    finally:
        r.close()
