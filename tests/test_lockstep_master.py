"""virtualaxis.master.LockstepMaster against `virtualaxis serve --lockstep` in another process (udp_multicast,
hop_limit 0): CSP / CSV / CST set-points from an array, a generator and a G-code-like file, one SYNC each, the
measured trace returned."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from served_drive import served

from virtualaxis.diagnosis.trace import read_trace
from virtualaxis.master import LockstepError, LockstepMaster, SetpointError, connect, gcode_setpoints


def _ramp(n: int, v_m_s: float, period_s: float = 0.001) -> np.ndarray:
    """A move at ``v_m_s`` from rest, smoothed over 50 cycles at each end."""
    t = np.arange(n) * period_s
    return np.clip(v_m_s * (t - 0.025), 0.0, None)


def test_csp_array_generator_and_gcode_stream_and_trace(tmp_path):
    with served("--lockstep") as s:
        net = connect(s.spec)
        try:
            with LockstepMaster(net, 1, mode="csp") as m:
                sp = _ramp(300, 0.05)  # 50 mm/s for ~0.3 s: 13.75 mm
                x0 = None
                trace = m.run(sp + 0.0)
                assert trace.setpoint.shape == (300, 1) and trace.position_m.shape == (300, 1)
                assert np.all(trace.statusword & 0x6F == 0x27)
                assert np.allclose(trace.t_s[1] - trace.t_s[0], 0.001)
                # the drive follows: the following error is a lag of a few cycles at 50 mm/s, not the target
                err = sp - trace.position_m[:, 0]
                assert abs(err[-1]) < 2e-3 and np.max(np.abs(err)) < 3e-3, (err[-1], np.max(np.abs(err)))
                assert trace.position_m[-1, 0] > 0.01
                x0 = float(trace.position_m[-1, 0])
                # a generator: back to 0 over 300 cycles
                gen = (x0 * (1 - k / 299) for k in range(300))
                back = m.run(gen)
                assert abs(back.position_m[-1, 0]) < 2e-3 and back.setpoint[-1, 0] == 0.0
                path = tmp_path / "p.ngc"
                path.write_text("G1 X5 F3000 ; 50 mm/s\nG4 P0.05\nG0 X0\n")
                g = m.run(path, axes="X")
                assert abs(g.position_m[:, 0].max() - 0.005) < 5e-4 and abs(g.position_m[-1, 0]) < 1e-3
                out = g.write(tmp_path / "g.csv")
                tr = read_trace(out)
                assert np.allclose(tr.columns["pos_cmd"], g.setpoint[:, 0]) and tr.t.size == g.t_s.size
                with pytest.raises(SetpointError, match="set-point 1"):
                    m.run([0.0, float("nan")])
        finally:
            net.disconnect()


def test_csv_and_cst_streams_move_the_axis():
    """CSV reaches the velocity streamed; CST: a torque of 30 % of the rated one, then the negative of it,
    accelerates the axis one way and then the other (the same served drive, one master after the other)."""
    with served("--lockstep") as s:
        net = connect(s.spec)
        try:
            with LockstepMaster(net, [1], mode="csv") as m:
                trace = m.run(np.full(200, 0.02))  # 20 mm/s
                assert abs(trace.velocity_m_s[-1, 0] - 0.02) < 2e-3, trace.velocity_m_s[-5:, 0]
                assert trace.position_m[-1, 0] - trace.position_m[0, 0] > 0.002
                m.run(np.zeros(100))  # to rest
            with LockstepMaster(net, [1], mode="cst") as m:
                torque_nm = 0.3 * m.rated_torque_nm[1]
                push = m.run(np.full(100, torque_nm))
                pull = m.run(np.full(100, -torque_nm))
                assert np.all(push.statusword & 0x6F == 0x27) and push.setpoint[0, 0] == torque_nm
                assert push.velocity_m_s[-1, 0] - push.velocity_m_s[0, 0] > 1e-3, push.velocity_m_s[::20, 0]
                assert pull.velocity_m_s[-1, 0] < push.velocity_m_s[-1, 0] - 1e-3, pull.velocity_m_s[::20, 0]
        finally:
            net.disconnect()


def test_gcode_setpoints_refuse_what_they_cannot_run(tmp_path):
    p = tmp_path / "a.ngc"
    p.write_text("G1 X1 F600\nG2 X0 Y1 I0 J1\n")
    with pytest.raises(SetpointError, match=r"a\.ngc:2: .*G2"):
        gcode_setpoints(p, axes="XY")
    p.write_text("G1 X1\n")
    with pytest.raises(SetpointError, match=r"a\.ngc:1: G1 without a feed"):
        gcode_setpoints(p)
    p.write_text("G1 X1 Q3 F100\n")
    with pytest.raises(SetpointError, match=r"a\.ngc:1: word\(s\) Q"):
        gcode_setpoints(p)
    p.write_text("G1 X10 F6000\n")  # 100 mm/s, 1 m/s^2: 0.1 s ramps, 10 mm
    sp = gcode_setpoints(p, period_s=0.001)
    assert sp.shape[1] == 1 and sp[0, 0] == 0.0 and abs(sp[-1, 0] - 0.010) < 1e-12
    v = np.diff(sp[:, 0]) / 0.001
    assert abs(v.max() - 0.1) < 1e-3 and np.all(v >= -1e-12)


def test_a_drive_that_opens_its_holding_brake_first_is_enabled(tmp_path):
    """A vertical axis whose brake opens in 200 ms (0x2040 commissioned from the config) stays SWITCHED ON for that
    long after 0x0F; the master waits for it in drive time (``enable_timeout_s``), and a shorter wait is a clear
    LockstepError naming the statusword."""
    from virtualaxis.config import load_axis_config
    from virtualaxis.runtime.axes import DEFAULT_CONFIG

    weight_n = load_axis_config(DEFAULT_CONFIG).mechanics.table_mass_kg * 9.80665
    cfg = tmp_path / "vertical.toml"
    cfg.write_text(Path(DEFAULT_CONFIG).read_text() + f"""
[effects]
force_offset_n = {{ value = {weight_n:.2f}, source = "table mass x g: a vertical axis" }}
brake_holding_force_n = {{ value = 3000.0, source = "test: brake holding 2 x the weight" }}
brake_opening_time_s = {{ value = 0.2, source = "test: a large brake" }}
brake_closing_time_s = {{ value = 0.05, source = "test" }}
""")
    with served("--lockstep", "--config", str(cfg)) as s:
        net = connect(s.spec)
        try:
            with pytest.raises(LockstepError, match=r"controlword 0x0F: statuswords node 1: 0x0633 after 100 SYNCs"):
                with LockstepMaster(net, 1, mode="csp", enable_timeout_s=0.1):
                    pass
            with LockstepMaster(net, 1, mode="csp") as m:
                assert m.node_ids == (1,)
                trace = m.run(_ramp(200, 0.02))
                assert np.all(trace.statusword & 0x6F == 0x27)
                assert trace.position_m[-1, 0] - trace.position_m[0, 0] > 1e-3
        finally:
            net.disconnect()
