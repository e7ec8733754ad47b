"""The axis as an FMI co-simulation FMU: exported by ``virtualaxis fmu`` (a subprocess), loaded, checked and run by
FMPy (an independent FMI host), compared with the simulator the ``simulate`` command runs on the same
zero-order-held input."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.fmi2 import FMU2Slave
from fmpy.validation import validate_fmu

from virtualaxis.config import load_axis_config
from virtualaxis.sim import layout as L
from virtualaxis.sim.batch import simulate_command
from virtualaxis.sim.simulator import AxisSimulator, ControlMode

ROOT = Path(__file__).resolve().parents[1]
SEED000 = ROOT / "configs" / "seed000-hust.toml"
#: a config with scale and current noise (the noise stream must be the simulator's)
NOISY = ROOT / "configs" / "examples" / "gap-bench-ballscrew.toml"
#: outputs compared with the simulator: relative to the signal's peak over the run
RTOL = 1e-9


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", *args], capture_output=True, text=True,
                          timeout=300)


def export(tmp_path: Path, config: Path, interface: str, *extra: str) -> Path:
    out = tmp_path / f"{config.stem}-{interface}.fmu"
    r = cli("fmu", "--config", str(config), "--out", str(out), "--interface", interface, *extra)
    assert r.returncode == 0, r.stderr
    assert validate_fmu(str(out)) == []
    return out


def held(values: np.ndarray, step_cycles: int, n_cycles: int) -> np.ndarray:
    """The inputs given at the communication points, held over each step, per position-loop cycle."""
    return np.repeat(values, step_cycles)[:n_cycles]


def close(name: str, got: np.ndarray, want: np.ndarray) -> None:
    scale = max(float(np.max(np.abs(want))), 1e-300)
    err = float(np.max(np.abs(got - want)))
    assert err <= RTOL * scale, f"{name}: max difference {err:.3g} (peak {scale:.3g})"


def run_fmu(fmu: Path, signals: dict[str, np.ndarray], t: np.ndarray, step_s: float, **kwargs) -> np.ndarray:
    sig = np.zeros(len(t), dtype=[("time", float)] + [(k, float) for k in signals])
    sig["time"] = t
    for k, v in signals.items():
        sig[k] = v
    return fmpy.simulate_fmu(str(fmu), stop_time=float(t[-1]), step_size=step_s, output_interval=step_s,
                             input=sig, **kwargs)


def test_position_interface_matches_the_simulator(tmp_path):
    fmu = export(tmp_path, SEED000, "position", "--step", "0.002")
    md = fmpy.read_model_description(str(fmu), validate=True)
    assert md.fmiVersion == "2.0" and md.coSimulation is not None
    assert md.defaultExperiment.stepSize == "0.002"
    vars_ = {v.name: v for v in md.modelVariables}
    # parameters: the config's values with the units their names carry and their sources
    lead = vars_["mechanics.lead_m"]
    assert (lead.causality, lead.unit, float(lead.start)) == ("parameter", "m", 0.016)
    assert "Table 2: pitch of the ball screw 16 mm" in lead.description
    assert vars_["control.speed_kp_nm_s_per_rad"].unit == "Nms/rad"
    assert vars_["motor.pole_pairs"].type == "Integer"
    assert {u.name for u in md.unitDefinitions} >= {"m", "m/s", "Nm", "A", "rad"}
    assert {n for n, v in vars_.items() if v.causality == "input"} == {
        "position_setpoint_m", "velocity_feedforward_m_s", "acceleration_feedforward_m_s2", "external_force_n"}
    with zipfile.ZipFile(fmu) as z:  # self-contained apart from the package: the config travels inside
        assert z.read("resources/axis.toml") == SEED000.read_bytes()

    cfg = load_axis_config(SEED000)
    cyc, step_s, k = cfg.control.position_cycle_s, 0.002, 2
    t = np.arange(0, 151) * step_s  # 0.3 s
    # a ramp with a reversal (backlash, friction), feed-forward inputs and a load step
    pos = 1e-3 + 0.02 * np.sin(2 * np.pi * 4 * t)
    vel = 0.02 * 2 * np.pi * 4 * np.cos(2 * np.pi * 4 * t)
    acc = -0.02 * (2 * np.pi * 4) ** 2 * np.sin(2 * np.pi * 4 * t)
    fext = np.where(t >= 0.1, 400.0, 0.0)
    res = run_fmu(fmu, {"position_setpoint_m": pos, "velocity_feedforward_m_s": vel,
                        "acceleration_feedforward_m_s2": acc, "external_force_n": fext}, t, step_s)
    assert len(res) == len(t)

    n = (len(t) - 1) * k + 1
    tc = np.arange(n) * cyc
    ref = simulate_command(cfg, tc, held(pos, k, n), held(fext, k, n), extras=True,
                           vel_cmd_m_s=held(vel, k, n), acc_cmd_m_s2=held(acc, k, n))
    rows = np.arange(len(t)) * k
    for col in ("pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q"):
        close(col, res[col], ref[col][rows])
    close("table_position_m", res["table_position_m"], ref["table_true"][rows])
    close("motor_speed_rad_s", res["motor_speed_rad_s"], ref["motor_speed"][rows])
    close("current_d_a", res["current_d_a"], ref["current_d"][rows])
    close("friction_force_n", res["friction_force_n"], ref["friction_force"][rows])
    close("motor_torque_nm", res["motor_torque_nm"], ref["airgap_torque"][rows])
    # FMPy reads the outputs at t_i before it sets the inputs of t_i: the set-point in the sample (pos_cmd,
    # following error, force_ext) is the one held over the step that ends there
    prev = np.concatenate([[0], np.arange(len(t) - 1)])
    close("pos_cmd", res["pos_cmd"], pos[prev])
    close("force_ext", res["force_ext"], fext[prev])
    close("following_error", res["following_error"], pos[prev] - ref["pos_fb"][rows])
    assert np.max(np.abs(ref["following_error"])) > 1e-5  # the axis moved and lagged: the comparison means something


def reference_rows(config: Path, mode: ControlMode, aux: np.ndarray, fext: np.ndarray, x0_m: float) -> np.ndarray:
    """The simulator's batch run in velocity / torque mode on per-cycle set-points: output rows (layout.O_*)."""
    sim = AxisSimulator(load_axis_config(config), initial_position_m=x0_m)
    sim.set_mode(mode)
    sim.enable(True)
    zeros = np.zeros(len(aux))
    return sim.run_arrays(np.full(len(aux), x0_m), zeros, zeros, fext, aux=aux)


SAMPLED = {"pos_meas": L.O_POS_MEAS, "pos_fb": L.O_POS_FB, "motor_pos": L.O_MOTOR_POS, "vel_meas": L.O_VEL,
           "torque_meas": L.O_TORQUE, "current_q": L.O_CURRENT_Q, "table_position_m": L.O_TABLE_TRUE,
           "motor_speed_rad_s": L.O_MOTOR_SPEED, "current_d_a": L.O_CURRENT_D, "friction_force_n": L.O_FRICTION,
           "motor_torque_nm": L.O_AIRGAP}


@pytest.mark.parametrize("interface, setpoint, mode", [
    ("speed", "velocity_setpoint_m_s", ControlMode.VELOCITY),
    ("torque", "torque_setpoint_nm", ControlMode.TORQUE),
])
def test_speed_and_torque_interfaces_match_the_simulator(tmp_path, interface, setpoint, mode):
    """On an axis with scale and current noise: the FMU draws the simulator's noise stream."""
    fmu = export(tmp_path, NOISY, interface)
    md = fmpy.read_model_description(str(fmu), validate=True)
    names = {v.name for v in md.modelVariables}
    assert {n for n in names if n.endswith(("_setpoint_m", "_feedforward_m_s"))} == set()  # no position loop input
    assert setpoint in names and "initial_position_m" in names
    assert "following_error" not in names and "pos_cmd" not in names  # the position loop is the importing tool's
    cfg = load_axis_config(NOISY)
    step_s, k = 0.003, 3
    t = np.arange(0, 81) * step_s  # 0.24 s
    if interface == "speed":  # forward, reverse through the backlash and friction
        u = 0.05 * np.sin(2 * np.pi * 5 * t)
    else:
        u = np.where(t < 0.08, 4.0, np.where(t < 0.16, -4.0, 0.5))
    fext = np.where(t >= 0.12, -200.0, 0.0)
    x0 = 0.01
    res = run_fmu(fmu, {setpoint: u, "external_force_n": fext}, t, step_s, start_values={"initial_position_m": x0})
    n = (len(t) - 1) * k + 1
    ref = reference_rows(NOISY, mode, held(u, k, n), held(fext, k, n), x0)
    rows = np.arange(len(t)) * k
    assert cfg.sensors.position_noise_m > 0 and np.std(np.diff(ref[:, L.O_POS_MEAS] - ref[:, L.O_TABLE_TRUE])) > 0
    for name, idx in SAMPLED.items():
        close(name, res[name], ref[rows, idx])
    assert np.ptp(ref[:, L.O_TABLE_TRUE]) > 1e-4  # the axis moved


def test_position_loop_in_the_importing_tool_matches_the_drives_own_loop(tmp_path):
    """Co-simulation: FMPy steps the speed-interface FMU one position cycle at a time; the position controller is
    here (P on the position feedback the FMU outputs, with speed feed-forward); the table follows as under the
    drive's own position loop (simulate_command on the same command)."""
    fmu = export(tmp_path, SEED000, "speed")
    cfg = load_axis_config(SEED000)
    kv_1_per_s, kff = cfg.control.kv_1_per_s, cfg.control.velocity_ff_factor
    assert cfg.control.torque_ff_factor == 0.0  # the speed interface has no torque feed-forward input
    cyc = cfg.control.position_cycle_s
    n = 301
    tc = np.arange(n) * cyc
    cmd = 0.002 + 0.01 * (1 - np.cos(2 * np.pi * 3 * tc))  # a move and back, through the reversal
    vff = 0.01 * 2 * np.pi * 3 * np.sin(2 * np.pi * 3 * tc)

    md = fmpy.read_model_description(str(fmu))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    slave = FMU2Slave(guid=md.guid, unzipDirectory=fmpy.extract(str(fmu)),
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName="cosim")
    slave.instantiate()
    try:
        slave.setupExperiment(startTime=0.0)
        slave.enterInitializationMode()
        slave.setReal([vr["initial_position_m"]], [float(cmd[0])])
        slave.exitInitializationMode()
        table, fb = np.zeros(n), np.zeros(n)
        for i in range(n):
            fb[i], table[i] = slave.getReal([vr["pos_fb"], vr["table_position_m"]])
            speed = kv_1_per_s * (cmd[i] - fb[i]) + kff * vff[i]
            slave.setReal([vr["velocity_setpoint_m_s"]], [speed])
            slave.doStep(currentCommunicationPoint=float(tc[i]), communicationStepSize=cyc)
        slave.terminate()
    finally:
        slave.freeInstance()

    ref = simulate_command(cfg, tc, cmd, extras=True, vel_cmd_m_s=vff, acc_cmd_m_s2=np.zeros(n))
    close("pos_fb", fb, ref["pos_fb"])
    close("table_position_m", table, ref["table_true"])
    assert np.max(np.abs(ref["following_error"])) > 1e-5
