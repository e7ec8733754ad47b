"""The axis as an FMI co-simulation FMU: exported by ``virtualaxis fmu`` (a subprocess), checked by FMPy's
model-description reader and validation, run by FMPy (an independent FMI host, in a child process:
tests/fmu_host.py says why), compared with the simulator the ``simulate`` command runs on the same zero-order-held
input."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import background
import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from virtualaxis.config import load_axis_config
from virtualaxis.sim import layout as L
from virtualaxis.sim.batch import simulate_command
from virtualaxis.sim.simulator import AxisSimulator, ControlMode

ROOT = Path(__file__).resolve().parents[1]
HOST = Path(__file__).with_name("fmu_host.py")
SEED000 = ROOT / "configs" / "seed000-hust.toml"
#: a config with scale and current noise (the noise stream must be the simulator's)
NOISY = ROOT / "configs" / "examples" / "gap-bench-ballscrew.toml"
#: outputs compared with the simulator: relative to the signal's peak over the run
RTOL = 1e-9


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())",
                           *args], capture_output=True, text=True, timeout=300)


def host(tmp_path: Path, job: str, **kwargs) -> dict:
    """Run a job of tests/fmu_host.py (FMPy) in a child process; its arrays."""
    spec = tmp_path / f"{job}.json"
    out = tmp_path / f"{job}.npz"
    plain = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in kwargs.items()}
    spec.write_text(json.dumps({"job": job, "out": str(out), **plain}))
    r = subprocess.run([sys.executable, str(HOST), str(spec)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    with np.load(out) as data:
        return {k: data[k] for k in data.files}


def export(folder: Path, config: Path, interface: str, *extra: str) -> Path:
    """The CLI builds the FMU; FMPy's validation finds no problem in it."""
    out = folder / f"{config.stem}-{interface}{''.join(extra).replace('-', '_')}.fmu"
    r = cli("fmu", "--config", str(config), "--out", str(out), "--interface", interface, *extra)
    assert r.returncode == 0, r.stderr
    assert validate_fmu(str(out)) == []
    return out


@pytest.fixture(scope="session")
def built(tmp_path_factory):
    """``built(config, interface, *options)``: the FMU, built by the CLI once per test session."""
    folder = tmp_path_factory.mktemp("fmus")
    cache: dict[tuple, Path] = {}

    def get(config: Path, interface: str, *extra: str) -> Path:
        key = (str(config), interface, extra)
        if key not in cache:
            cache[key] = export(folder, config, interface, *extra)
        return cache[key]
    return get


def held(values: np.ndarray, step_cycles: int, n_cycles: int) -> np.ndarray:
    """The inputs given at the communication points, held over each step, per position-loop cycle."""
    return np.repeat(values, step_cycles)[:n_cycles]


def close(name: str, got: np.ndarray, want: np.ndarray) -> None:
    scale = max(float(np.max(np.abs(want))), 1e-300)
    err = float(np.max(np.abs(got - want)))
    assert err <= RTOL * scale, f"{name}: max difference {err:.3g} (peak {scale:.3g})"


def run_fmu(tmp_path: Path, fmu: Path, signals: dict[str, np.ndarray], t: np.ndarray, step_s: float,
            **kwargs) -> dict:
    return host(tmp_path, "simulate", fmu=str(fmu), time=t, step_s=step_s,
                inputs={k: np.asarray(v, float).tolist() for k, v in signals.items()}, **kwargs)


def test_position_interface_matches_the_simulator(tmp_path, built):
    fmu = built(SEED000, "position", "--step", "0.002")
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
    res = run_fmu(tmp_path, fmu, {"position_setpoint_m": pos, "velocity_feedforward_m_s": vel,
                        "acceleration_feedforward_m_s2": acc, "external_force_n": fext}, t, step_s)
    assert len(res["time"]) == len(t)

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


def test_a_step_of_current_cycles_matches_the_simulator(tmp_path, built):
    """FMPy steps the position-interface FMU by 3 current-loop cycles (93.75 us; a position cycle is 32 of them):
    at the position-loop instants the outputs are the simulator's; between them the axis state is the one the
    kernel passes through (its feedback ring, recorded every current cycle) and the drive's channels hold the
    sample of the cycle under way. The drive samples the set-points in force at each position-loop instant."""
    cfg = load_axis_config(SEED000)
    hc, cyc = cfg.control.current_cycle_s, cfg.control.position_cycle_s
    per, k = round(cyc / hc), 3
    fmu = built(SEED000, "position", "--step", repr(k * hc))
    n_steps = 640  # 0.06 s
    t = np.arange(n_steps + 1) * (k * hc)
    pos = 1e-3 * np.sin(2 * np.pi * 25 * t) + np.where(t >= 0.03, 2e-4, 0.0)  # changes at every step
    fext = np.where(t >= 0.02, 300.0, 0.0)
    res = run_fmu(tmp_path, fmu, {"position_setpoint_m": pos, "external_force_n": fext}, t, k * hc)
    assert len(res["time"]) == n_steps + 1
    # the set-point the drive samples at position-loop instant j: the input of the last step that began by then
    n_cyc = n_steps * k // per + 1
    given = (np.arange(n_cyc) * per) // k
    ref = simulate_command(cfg, np.arange(n_cyc) * cyc, pos[given], fext[given], extras=True)
    ticks = np.arange(n_steps + 1) * k
    cycle, within = ticks // per, ticks % per
    at = within == 0
    assert at.sum() >= 20 and (~at).sum() > 500
    for col in ("pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q"):
        close(col, res[col][at], ref[col][cycle[at]])
        close(f"{col} (held)", res[col][~at], ref[col][cycle[~at]])
    close("table_position_m", res["table_position_m"][at], ref["table_true"][cycle[at]])
    close("motor_speed_rad_s", res["motor_speed_rad_s"][at], ref["motor_speed"][cycle[at]])
    close("current_d_a", res["current_d_a"][at], ref["current_d"][cycle[at]])
    # between the instants: the table position and motor angle of each current cycle, as the kernel records them
    sim = AxisSimulator(cfg, initial_position_m=float(pos[0]))
    sim.enable(True)
    table, angle = np.zeros((n_cyc, per)), np.zeros((n_cyc, per))
    for j in range(n_cyc):
        sim.set_position_setpoint(float(pos[given[j]]))
        sim.set_external_force(float(fext[given[j]]))
        table[j, 0], angle[j, 0] = sim.state.table_position_m, sim.state.motor_angle_rad
        sim.advance(1)
        last = int(sim.st[L.S_RING])
        rows = (last - per + np.arange(1, per)) % L.RING_SIZE
        table[j, 1:], angle[j, 1:] = sim.ring[rows, 1], sim.ring[rows, 0]
    close("table_position_m (all)", res["table_position_m"], table[cycle, within])
    close("motor_angle_rad (all)", res["motor_angle_rad"], angle[cycle, within])
    assert np.ptp(table[:, 1:] - table[:, :1]) > 1e-7  # the table moves within a position cycle


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
def test_speed_and_torque_interfaces_match_the_simulator(tmp_path, built, interface, setpoint, mode):
    """On an axis with scale and current noise: the FMU draws the simulator's noise stream."""
    fmu = built(NOISY, interface)
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
    res = run_fmu(tmp_path, fmu, {setpoint: u, "external_force_n": fext}, t, step_s,
                  start_values={"initial_position_m": x0})
    n = (len(t) - 1) * k + 1
    ref = reference_rows(NOISY, mode, held(u, k, n), held(fext, k, n), x0)
    rows = np.arange(len(t)) * k
    assert cfg.sensors.position_noise_m > 0 and np.std(np.diff(ref[:, L.O_POS_MEAS] - ref[:, L.O_TABLE_TRUE])) > 0
    for name, idx in SAMPLED.items():
        close(name, res[name], ref[rows, idx])
    assert np.ptp(ref[:, L.O_TABLE_TRUE]) > 1e-4  # the axis moved


def test_position_loop_in_the_importing_tool_matches_the_drives_own_loop(tmp_path, built):
    """Co-simulation: FMPy steps the speed-interface FMU one position cycle at a time; the position controller is
    here (P on the position feedback the FMU outputs, with speed feed-forward); the table follows as under the
    drive's own position loop (simulate_command on the same command)."""
    fmu = built(SEED000, "speed")
    cfg = load_axis_config(SEED000)
    kv_1_per_s, kff = cfg.control.kv_1_per_s, cfg.control.velocity_ff_factor
    assert cfg.control.torque_ff_factor == 0.0  # the speed interface has no torque feed-forward input
    cyc = cfg.control.position_cycle_s
    n = 301
    tc = np.arange(n) * cyc
    cmd = 0.002 + 0.01 * (1 - np.cos(2 * np.pi * 3 * tc))  # a move and back, through the reversal
    vff = 0.01 * 2 * np.pi * 3 * np.sin(2 * np.pi * 3 * tc)

    res = host(tmp_path, "cosim", fmu=str(fmu), cmd=cmd, vff=vff, kv_1_per_s=kv_1_per_s, kff=kff, cycle_s=cyc)
    fb, table = res["pos_fb"], res["table_position_m"]

    ref = simulate_command(cfg, tc, cmd, extras=True, vel_cmd_m_s=vff, acc_cmd_m_s2=np.zeros(n))
    close("pos_fb", fb, ref["pos_fb"])
    close("table_position_m", table, ref["table_true"])
    assert np.max(np.abs(ref["following_error"])) > 1e-5


@pytest.mark.parametrize("args, says", [
    (["--interface", "current"], "invalid choice: 'current'"),
    (["--step", "0.00101"], "--step: 0.00101 s is not a whole number of current-loop cycles"),
    (["--step", "nan"], "--step: must be a finite number > 0 s"),
])
def test_bad_export_options_get_one_error_line(tmp_path, args, says):
    out = tmp_path / "axis.fmu"
    r = cli("fmu", "--config", str(SEED000), "--out", str(out), *args)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and says in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()


def test_bad_output_and_config_get_one_error_line(tmp_path):
    r = cli("fmu", "--config", str(SEED000), "--out", str(tmp_path / "axis.zip"))
    assert r.returncode == 2 and "--out:" in r.stderr and "ends in .fmu" in r.stderr, r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text(SEED000.read_text().replace("lead_m = { value = 0.016", "lead_m = { value = -0.016"))
    r = cli("fmu", "--config", str(bad), "--out", str(tmp_path / "axis.fmu"))
    assert r.returncode == 2 and "mechanics.lead_m" in r.stderr and "Traceback" not in r.stderr, r.stderr
    (tmp_path / "axis.fmu").write_bytes(b"keep")
    r = cli("fmu", "--config", str(SEED000), "--out", str(tmp_path / "axis.fmu"))
    assert r.returncode == 2 and "exists" in r.stderr and (tmp_path / "axis.fmu").read_bytes() == b"keep"


def test_without_pythonfmu_the_command_says_what_to_install(tmp_path):
    code = ("import sys; sys.modules['pythonfmu'] = None; from virtualaxis.cli.main import main; "
            f"sys.exit(main(['fmu', '--config', {str(SEED000)!r}, '--out', {str(tmp_path / 'a.fmu')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "pip install 'virtualaxis[fmu]'" in r.stderr, r.stderr


def test_the_fmu_refuses_bad_steps_inputs_and_parameters(tmp_path, built):
    """At run time: a communication step that is not whole position cycles, a non-finite input and a parameter
    the config refuses are errors reported to the importing tool, not a wrong or silent result; a valid
    parameter change is simulated."""
    fmu = built(SEED000, "position")
    cases = [
        {"step_s": 0.00101},
        {"step_s": 0.001, "inputs": {"position_setpoint_m": float("nan")}},
        {"step_s": 0.001, "parameters": {"mechanics.lead_m": -0.016}},
        # a parameter the config accepts: the FMU runs the changed axis
        {"step_s": 0.001, "steps": 60, "parameters": {"control.kv_per_s": 40.0, "position_setpoint_m": 0.0},
         "inputs": {"position_setpoint_m": 1e-3}},
    ]
    res = host(tmp_path, "refusals", fmu=str(fmu), cases=cases)
    assert str(res["failed0"]) == "doStep", res["log0"]
    assert "0.00101 s is not a whole number of current-loop cycles" in str(res["log0"])
    assert str(res["failed1"]) == "setReal", res["log1"]
    assert "input position_setpoint_m must be finite (got nan)" in str(res["log1"]), res["log1"]
    assert str(res["failed2"]) == "exitInitializationMode" and "mechanics.lead_m" in str(res["log2"]), res["log2"]
    assert str(res["failed3"]) == "", res["log3"]
    # the axis starts at rest at the set-point given at initialisation (0), the set-point 1 mm from the first step
    fe = {}
    for kv in (40.0, None):
        cfg = load_axis_config(SEED000)
        sim = AxisSimulator(cfg.replace(control={"kv_per_s": kv}) if kv else cfg, initial_position_m=0.0)
        sim.enable(True)
        zeros = np.zeros(60)
        fe[kv] = sim.run_arrays(np.full(60, 1e-3), zeros, zeros, zeros)[:, L.O_FOLLOWING]
    close("following_error", res["fe3"], fe[40.0])
    assert np.max(np.abs(fe[None] - fe[40.0])) > 1e-6  # the parameter mattered


def every_shipped_config(tmp_path: Path) -> dict:
    """configs/*.toml and configs/examples/*.toml, the interfaces in turn: each FMU built by the CLI and validated
    by FMPy (:func:`export`), then run by FMPy for 10 communication steps (a background job of the suite:
    tests/background.py)."""
    from virtualaxis.fmu.export import INTERFACES

    configs = sorted((ROOT / "configs").glob("*.toml")) + sorted((ROOT / "configs" / "examples").glob("*.toml"))
    fmus = [str(export(tmp_path, cfg, INTERFACES[i % len(INTERFACES)])) for i, cfg in enumerate(configs)]
    return {"configs": configs, "res": host(tmp_path, "smoke", fmus=fmus, stop_s=0.01)}


@pytest.mark.slow
@pytest.mark.background("every_shipped_config")
def test_every_shipped_config_exports_a_valid_running_fmu(request):
    """configs/*.toml and configs/examples/*.toml, the interfaces in turn: the CLI builds each FMU, FMPy validates
    its model description and runs it for 10 communication steps."""
    job = background.result(request.config, "every_shipped_config")
    configs, res = job["configs"], job["res"]
    assert len(configs) >= 5
    for k, cfg in enumerate(configs):
        assert str(res[f"problems{k}"]) == "" and bool(res[f"finite{k}"]) and int(res[f"rows{k}"]) == 11, cfg


def test_an_fmpy_script_exits_cleanly(tmp_path, built):
    """FMPy as in a user's script (simulate_fmu instantiates, frees and unloads the FMU; output to files): the
    process exits with status 0, run after run (no heap corruption at exit)."""
    fmu = built(SEED000, "position")
    script = ("import sys, fmpy; r = fmpy.simulate_fmu(sys.argv[1], stop_time=0.02, step_size=0.001); "
              "print(len(r), r['pos_fb'][-1])")
    for run in range(3):
        out, err = tmp_path / f"out{run}.txt", tmp_path / f"err{run}.txt"
        with out.open("w") as fout, err.open("w") as ferr:
            rc = subprocess.run([sys.executable, "-c", script, str(fmu)], stdout=fout, stderr=ferr,
                                timeout=300).returncode
        assert rc == 0, f"run {run}: exit status {rc}: {err.read_text()[-2000:]}"
        assert out.read_text().startswith("21 ")


def test_preview_is_the_row_the_next_cycle_records_and_changes_nothing():
    """AxisSimulator.preview(): the drive's sample now (noise included), without advancing the axis or the noise."""
    cfg = load_axis_config(NOISY)
    n = 300  # past one block of drawn-ahead noise (simulator.NOISE_BLOCK = 256)
    pos = 0.002 * np.sin(np.arange(n + 1) * 0.05)
    ref = AxisSimulator(cfg)
    ref.enable(True)
    zeros = np.zeros(n + 1)
    want = ref.run_arrays(pos, zeros, zeros, zeros)
    sim = AxisSimulator(cfg)
    sim.enable(True)
    for j in range(n + 1):
        sim.set_position_setpoint(float(pos[j]))
        before = (sim.state, sim.time_s)
        first = sim.preview().copy()
        np.testing.assert_array_equal(sim.preview(), first)
        assert (sim.state, sim.time_s) == before
        np.testing.assert_array_equal(first, want[j])
        sim.advance(1)


def test_state_within_cycle_is_the_state_the_cycle_passes_through():
    """AxisSimulator.state_within_cycle(m): the state m current-loop cycles into the next position cycle, as the
    kernel records it while it runs that cycle (its feedback ring: table position and motor angle per current
    cycle), without advancing the axis."""
    cfg = load_axis_config(NOISY)
    sim = AxisSimulator(cfg)
    sim.enable(True)
    per, hc = sim.current_cycles_per_cycle, cfg.control.current_cycle_s
    assert per == round(cfg.control.position_cycle_s / hc) > 1
    for j in range(6):
        sim.set_position_setpoint(2e-4 * j)
        sim.set_external_force(100.0 * (j % 2))
        before = (sim.state, sim.time_s)
        probes = [sim.state_within_cycle(m) for m in range(per)]
        assert (sim.state, sim.time_s) == before and probes[0] == before[0]
        sim.advance(1)
        rows = (int(sim.st[L.S_RING]) - per + np.arange(1, per)) % L.RING_SIZE
        np.testing.assert_array_equal([p.table_position_m for p in probes[1:]], sim.ring[rows, 1])
        np.testing.assert_array_equal([p.motor_angle_rad for p in probes[1:]], sim.ring[rows, 0])
        np.testing.assert_allclose([p.time_s for p in probes], before[1] + np.arange(per) * hc, rtol=0, atol=1e-12)
    assert np.ptp([p.table_position_m for p in probes]) > 0  # the table moved within the cycle
    with pytest.raises(ValueError, match="current_cycles must be in"):
        sim.state_within_cycle(per)
