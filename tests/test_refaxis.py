"""Reference axis (virtualaxis.refaxis): independence from the diagnosed model, the case API, and physics
checked against closed-form results derived on paper (docs/refaxis.md, "Checks")."""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.refaxis import axes as A
from virtualaxis.refaxis import case_names, make_case
from virtualaxis.refaxis import commands as C
from virtualaxis.refaxis import kernel as K
from virtualaxis.refaxis import run as R

PKG = Path(A.__file__).resolve().parent
FORBIDDEN = ("virtualaxis.sim", "virtualaxis.plant", "virtualaxis.control", "virtualaxis.diagnosis")


def test_imports_nothing_from_the_diagnosed_model():
    """Every module of the package is parsed; its only virtualaxis imports are virtualaxis.refaxis itself."""
    files = sorted(PKG.glob("*.py"))
    assert len(files) >= 5
    for f in files:
        tree = ast.parse(f.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{f.name}: relative import"
                mods = [node.module or ""]
            else:
                continue
            for m in mods:
                assert not m.startswith(FORBIDDEN), f"{f.name} imports {m}"
                if m.startswith("virtualaxis"):
                    assert m.startswith("virtualaxis.refaxis"), f"{f.name} imports {m}"


def test_case_names_cover_every_effect_and_the_pairs():
    names = case_names()
    assert len(names) == len(set(names)) >= 30
    tm = case_names("two_mass")
    effects = ["backlash", "coulomb_friction", "stribeck_friction", "viscous_friction", "friction_asymmetry",
               "mass_error", "axial_compliance", "resonance", "lead_error", "torque_ripple", "time_delay",
               "thermal_drift"]
    for e in effects + ["clean", "coulomb_friction+viscous_friction", "backlash+coulomb_friction",
                        "mass_error+time_delay"]:
        assert f"two_mass/{e}" in tm
    assert "rigid_pp/clean" in case_names("rigid_pp")
    with pytest.raises(ValueError, match="unknown structure"):
        case_names("three_mass")
    with pytest.raises(KeyError, match="unknown reference case"):
        make_case("two_mass/nothing", Path("/nonexistent"))


@pytest.mark.parametrize("name", ["two_mass/backlash", "full_closed/time_delay", "rigid_pp/channel_shift",
                                  "rigid_pp/moving_start"])
def test_make_case_writes_a_loadable_config_traces_and_truth(tmp_path, name):
    cf = make_case(name, tmp_path, seed=3, quick=True)
    cfg = load_axis_config(cf.config_path)  # our schema, validated on load
    assert cfg.mechanics.model == ("rigid" if name.startswith("rigid") else "two_mass")
    assert cfg.control.position_feedback == ("motor_encoder" if name.startswith("two") else "linear_scale")
    assert not cfg.backlash.enabled and cfg.sensors.dead_time_s == 0  # the withheld effect is not in the config
    for key, src in cfg.sources.items():
        assert src.strip(), key
    assert len(cf.fit) == 4 and len(cf.holdout) == (4 if name.startswith("rigid") else 3)
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth == json.loads(json.dumps(cf.truth))
    assert set(cf.truth) >= {"effects", "params", "main_param", "notes"}
    for eff, key in cf.truth["main_param"].items():
        assert eff in cf.truth["effects"] and key in cf.truth["params"]
    assert all(isinstance(v, (int, float)) for v in cf.truth["params"].values())
    header = cf.fit[0].read_text().splitlines()[0].split(",")
    expect = ["t", "pos_cmd", "pos_meas", "force_drive"]
    if not name.startswith("rigid"):
        expect += ["motor_pos", "current_q"]
    if name.startswith("two"):
        expect += ["pos_fb"]
    assert set(header) == set(expect)
    if name.startswith("rigid"):  # the validation run with known force pulses
        pulses = np.genfromtxt(cf.holdout[-1], delimiter=",", names=True)
        assert cf.holdout[-1].stem == "heldout_pulses" and set(np.unique(pulses["force_ext"])) == {-40.0, 0.0, 40.0}
    d = np.genfromtxt(cf.fit[0], delimiter=",", names=True)
    assert np.allclose(np.diff(d["t"]), 1e-3)
    assert np.all(np.isfinite(d.view(float).reshape(len(d), -1)))


# ---------------------------------------------------------------------------------------------------------
# physics against closed-form results
# ---------------------------------------------------------------------------------------------------------
def _p(structure: str, **changes) -> np.ndarray:
    phys = dict(A.NOMINAL[structure])
    kp = A.kernel_params(structure, phys)
    kp.update(changes)
    return K.param_vector(kp)


def _step_matrices(p: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear step map s+ = Ad s + Bd u of the kernel's RK4 step (friction and backlash off: exact by superposition)."""
    ad = np.zeros((6, 6))
    for i in range(6):
        s = np.zeros(6)
        s[i] = 1.0
        K.mech_step(p, s, 0.0, 0.0, 0.0, 0.0, h)
        ad[:, i] = s
    s = np.zeros(6)
    K.mech_step(p, s, 1.0, 0.0, 0.0, 0.0, h)
    return ad, s.copy()


def test_two_mass_frf_resonance_and_antiresonance_match_the_formulas():
    """Motor speed / motor torque of the two-mass model: resonance sqrt(k (1/m_m + 1/m_t)), anti-resonance
    sqrt(k / m_t), m_m = J / r^2 — from the kernel's discrete step map at h = 31.25 us (undamped)."""
    phys = A.NOMINAL["two_mass"]
    p = _p("two_mass", sigma0_n_per_m=0.0, sigma1_n_s_per_m=0.0, fv_pos_n_s_per_m=0.0, fv_neg_n_s_per_m=0.0,
           c_ax_n_s_per_m=0.0, bm_nm_s_per_rad=0.0, ea_n=0.0)
    h = phys["speed_cycle_s"] / phys["substeps"]
    wa, wr = A.two_mass_frequencies(phys)
    ad, bd = _step_matrices(p, h)
    lam = np.linalg.eigvals(ad)
    w_modes = np.abs(np.angle(lam)) / h
    w_osc = w_modes[w_modes > 1.0]
    assert w_osc.size == 2 and np.allclose(w_osc, wr, rtol=1e-6)  # the +-j pair
    f = np.linspace(80, 220, 14001)  # Hz, 0.01 Hz grid
    z = np.exp(1j * 2 * np.pi * f * h)
    c = np.zeros(6)
    c[1] = 1.0  # motor speed
    eye = np.eye(6)
    mag = np.array([abs(c @ np.linalg.solve(zz * eye - ad, bd)) for zz in z])
    f_peak = f[np.argmax(mag)]
    f_notch = f[np.argmin(mag)]
    assert f_peak == pytest.approx(wr / 2 / np.pi, abs=0.02)
    assert f_notch == pytest.approx(wa / 2 / np.pi, abs=0.02)
    assert 120 < f_notch < 135 and 150 < f_peak < 170  # the nominal axis: 127 Hz / 159 Hz


def test_rk4_conserves_the_energy_of_the_undamped_mechanics():
    """Two-mass + resonant sub-mass, no damping, no friction, free vibration for 1 s (32000 steps):
    E = J w^2/2 + m v^2/2 + k d^2/2 + m_r v_r^2/2 + k_r (x_r - x)^2/2 never grows and loses at most what RK4's
    amplification |R(j w h)|^2 = 1 - (w h)^6 / 72 + ... predicts for the fastest mode (w h = 0.031: 2.2e-7)."""
    phys = dict(A.NOMINAL["two_mass"], resonance_hz=60.0, resonance_mass_kg=30.0, resonance_damping=0.0)
    kp = A.kernel_params("two_mass", phys)
    kp.update(sigma0_n_per_m=0.0, sigma1_n_s_per_m=0.0, fv_pos_n_s_per_m=0.0, fv_neg_n_s_per_m=0.0,
              c_ax_n_s_per_m=0.0, bm_nm_s_per_rad=0.0, ea_n=0.0)
    p = K.param_vector(kp)
    h = phys["speed_cycle_s"] / phys["substeps"]
    s0 = np.array([0.0, 20.0, 5e-6, -0.01, 2e-5, 0.05])
    out = K.open_loop(p, s0, np.zeros(32000), h)
    r, j, m, k = kp["r_m_per_rad"], kp["j_kg_m2"], kp["m_kg"], kp["k_mid_n_per_m"]
    mr, kr = kp["mr_kg"], kp["kr_n_per_m"]

    def energy(s):
        d = r * s[..., 0] - s[..., 2]
        return (0.5 * j * s[..., 1] ** 2 + 0.5 * m * s[..., 3] ** 2 + 0.5 * k * d**2 + 0.5 * mr * s[..., 5] ** 2
                + 0.5 * kr * (s[..., 4] - s[..., 2]) ** 2)

    e0 = energy(s0)
    e = energy(out[:, :6])
    w_fast = max(A.two_mass_frequencies(phys)[1], 2 * np.pi * 60.0) * 1.05  # the sub-mass stiffens the top mode
    bound = 32000 * (w_fast * h) ** 6 / 72
    assert np.all(e <= e0 * (1 + 1e-12))
    assert (e0 - e[-1]) / e0 < bound
    assert np.ptp(r * out[:, 0] - out[:, 2]) > 1e-5  # it did vibrate


@pytest.mark.parametrize("structure", ["two_mass", "full_closed", "rigid_pp"])
def test_following_error_without_feed_forward_is_v_over_kv(structure):
    """Constant-speed ramp, no feed-forward: e = v / Kv for the PI speed loop (two_mass on the encoder,
    full_closed on the scale; friction on: the integral term carries it); for the P/P cascade with friction
    e = v / Kv + (F_c + F_v v) / (K_p Kv)."""
    phys = dict(A.NOMINAL[structure], velocity_ff=0.0)
    v = 0.05
    n = 3000
    t = np.arange(n) * 1e-3
    x = np.where(t < 0.2, -0.05, -0.05 + v * (t - 0.2))
    tr = R.simulate(structure, phys, x, seed=1)
    fb = tr["pos_fb"] if structure == "two_mass" else tr["pos_meas"]  # what the position loop closes on
    e = (tr["pos_cmd"] - fb)[-1000:].mean()
    expect = v / phys["kv_per_s"]
    if structure == "rigid_pp":
        expect += (phys["coulomb_n"] + phys["viscous_n_s_per_m"] * v) / (phys["speed_kp"] * phys["kv_per_s"])
    assert e == pytest.approx(expect, rel=2e-3)


@pytest.mark.parametrize("stribeck", [0.0, 15.0])
def test_breakaway_force_is_coulomb_plus_stribeck(stribeck):
    """Rigid mass at rest, open-loop force ramped at 5 N/s: gross sliding (10 um) starts when the force has
    passed F_c + F_s (LuGre static level), within the ramp's 2 % overshoot; below it only pre-sliding."""
    phys = dict(A.NOMINAL["rigid_pp"], stribeck_n=stribeck)
    p = A.kernel_vector("rigid_pp", phys)
    h = 1e-3 / phys["substeps"]
    n = int(12.0 / h)
    u = 5.0 * np.arange(n) * h
    out = K.open_loop(p, np.zeros(6), u, h)
    i = int(np.argmax(out[:, 2] > 10e-6))
    f_break = u[i]
    level = phys["coulomb_n"] + stribeck
    assert level <= f_break <= 1.02 * level
    # pre-sliding below the level: LuGre dz/dx = 1 - sigma0 z / g -> x(F) = -(g / sigma0) ln(1 - F / g)
    below = out[u <= 0.9 * level, 2]
    assert below.max() == pytest.approx(-(level / p[K.P_SIGMA0_N_PER_M]) * math.log(0.1), rel=0.02)


def test_backlash_lost_motion_at_reversal():
    """Semi-closed loop, slow sine: the motor-to-table offset pos_fb - pos_meas jumps at reversal by
    gap + 2 F / k, F = F_c + F_v v the friction carried across the spring at mid-stroke (a = 0)."""
    gap = 12e-6
    phys = dict(A.NOMINAL["two_mass"], gap_m=gap)

    x = C.sine(1000, 0.01, 1)
    tr = R.simulate("two_mass", phys, x, seed=2)
    d = tr["pos_fb"] - tr["pos_meas"]
    v = np.gradient(tr["pos_cmd"], 1e-3)
    mid = np.where(np.diff(np.sign(tr["pos_cmd"])) != 0)[0]  # mid-stroke crossings (+v then -v)
    assert len(mid) == 2
    lv = [d[i - 25:i + 25].mean() for i in mid]
    vpk = abs(v[mid[0]])
    force = phys["coulomb_n"] + phys["viscous_n_s_per_m"] * vpk
    expect = gap + 2 * force / phys["axial_stiffness_n_per_m"]
    assert lv[0] - lv[1] == pytest.approx(expect, rel=0.03)


def test_thermal_and_lead_error_kinematics_at_standstill():
    """Standstill at x: pos_meas - pos_fb = (d0 + x (1 + eps)) (1 + alpha dT) - d0 - x + A sin(x / r + phi)
    (the spring carries no force at rest)."""
    phys = dict(A.NOMINAL["two_mass"], lead_error_ppm=40.0, lead_error_periodic_m=1.5e-6, lead_error_phase_rad=0.7,
                initial_temperature_rise_k=3.5)
    for x0 in (-0.04, 0.03):
        tr = R.simulate("two_mass", phys, np.full(800, x0), seed=4)
        meas = (tr["pos_meas"] - tr["pos_fb"])[-300:].mean()
        r = A.radius_m_per_rad(phys)
        eps, a_dt = 40e-6, 11.5e-6 * 3.5
        d0 = phys["nut_distance_m"]
        expect = (d0 + x0 * (1 + eps)) * (1 + a_dt) - d0 - x0 + 1.5e-6 * math.sin(x0 / r + 0.7)
        assert meas == pytest.approx(expect, abs=2e-8)


def test_cli_writes_cases_and_rejects_unknown_names(tmp_path, capsys):
    from virtualaxis.refaxis.__main__ import main

    assert main(["--out", str(tmp_path), "--quick", "--plot", "--cases", "rigid_pp/clean"]) == 0
    assert (tmp_path / "rigid_pp__clean" / "truth.json").exists() and (tmp_path / "timing.json").exists()
    assert (tmp_path / "rigid_pp__clean" / "traces.png").stat().st_size > 10_000
    assert main(["--out", str(tmp_path), "--cases", "rigid_pp/nothing"]) == 2
    assert "unknown case(s) rigid_pp/nothing" in capsys.readouterr().err


def test_sensor_quantisation_steps(tmp_path):
    """Recorded channels lie on their sensors' grids: 2 pi / 2^20 rad, 20 nm, 80 A / 2^14; rigid scale 0.1 um,
    force command 0.05 N; noise makes single-quantum steps appear."""
    cf = make_case("two_mass/clean", tmp_path / "tm", quick=True)
    d = np.genfromtxt(cf.fit[0], delimiter=",", names=True)
    for col, q in (("motor_pos", 2 * np.pi / 2**20), ("pos_meas", 2e-8), ("current_q", 80 / 2**14)):
        k = d[col] / q
        assert np.max(np.abs(k - np.round(k))) < 1e-3, col
        steps = np.abs(np.diff(np.round(k)))
        assert steps[steps > 0].min() == 1, col
    cf = make_case("rigid_pp/clean", tmp_path / "rp", quick=True)
    d = np.genfromtxt(cf.fit[0], delimiter=",", names=True)
    for col, q in (("pos_meas", 1e-7), ("force_drive", 0.05)):
        k = d[col] / q
        assert np.max(np.abs(k - np.round(k))) < 1e-3, col


def test_channel_shift_and_speed_estimator_cases_differ_as_stated(tmp_path):
    """channel_shift: the force column equals the clean-convention column moved one row earlier (same noise);
    the two-sample speed estimator changes the loop (different force)."""
    phys = A.NOMINAL["rigid_pp"]

    x = C.sine(3000, 0.01, 1)
    base = R.simulate("rigid_pp", phys, x, seed=7)
    shifted = R.simulate("rigid_pp", phys, x, seed=7, channel_shift=1)
    assert np.array_equal(shifted["force_drive"][:-1], base["force_drive"][1:])
    assert np.array_equal(shifted["pos_meas"], base["pos_meas"])
    two = R.simulate("rigid_pp", dict(phys, speed_estimator_samples=2.0), x, seed=7)
    assert np.abs(two["force_drive"] - base["force_drive"]).max() > 1.0


# rms sensor noise per channel: scale, encoder (r x 6e-6 rad), current (and its force), rigid force command
NOISE_FLOOR = {"pos_meas": 4e-8, "pos_fb": 2e-8, "force_drive": 5.8, "current_q": 0.015, "motor_pos": 6e-6}
NOISE_FLOOR_RIGID = {"pos_meas": 3e-8, "force_drive": 0.2}


@pytest.mark.parametrize("structure", ["two_mass", "full_closed", "rigid_pp"])
def test_every_withheld_effect_changes_the_traces_beyond_the_sensor_noise(structure):
    """Truth vs nominal config values, same noise draws, on the quick rapid traverse: every case but the clean
    one moves some channel by more than 3 x its sensor noise (rms), the clean case by exactly nothing."""
    from virtualaxis.refaxis.cases import CONFIG_OVERRIDES, SPECS, conditions

    fit, _ = conditions(structure, quick=True)
    cmds = [x for stem, x in fit if stem == "rapid"]
    floors = NOISE_FLOOR_RIGID if structure == "rigid_pp" else NOISE_FLOOR
    for name in case_names(structure):
        spec = SPECS[name]
        nominal = dict(A.NOMINAL[structure], **CONFIG_OVERRIDES.get(name, {}))
        truth = dict(A.NOMINAL[structure], **spec.truth)
        worst = 0.0
        for x in cmds:
            a = R.simulate(structure, nominal, x, seed=11)
            b = R.simulate(structure, truth, x, seed=11, channel_shift=spec.channel_shift)
            for col, sigma in floors.items():
                if col in a:
                    worst = max(worst, float(np.sqrt(np.mean((a[col] - b[col]) ** 2))) / sigma)
        if spec.name == "clean" or spec.moving_start:  # moving_start: same run, recorded from a later sample
            assert worst == 0.0, name
        else:
            assert worst > 3.0, f"{name}: largest change {worst:.2f} x the noise"


def test_encoder_dead_time_shifts_the_feedback_by_v_times_d():
    """Semi-closed loop at constant speed: the delayed encoder reads r theta(t - d) = r theta(t) - v d, the
    (undelayed) scale is unchanged, so pos_meas - pos_fb grows by exactly v d (50 mm/s x 0.6 ms = 30 um)."""
    v, d = 0.05, 6e-4
    t = np.arange(2500) * 1e-3
    x = np.where(t < 0.2, -0.05, -0.05 + v * (t - 0.2))
    gaps = []
    for delay in (0.0, d):
        tr = R.simulate("two_mass", dict(A.NOMINAL["two_mass"], dead_time_s=delay), x, seed=5)
        gaps.append((tr["pos_meas"] - tr["pos_fb"])[-800:].mean())
    assert gaps[1] - gaps[0] == pytest.approx(v * d, rel=0.01)
