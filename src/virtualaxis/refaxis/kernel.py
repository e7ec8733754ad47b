"""Compiled core of the reference axis: mechanics, friction, actuator lag, sensors and the digital cascade.

Written apart from ``virtualaxis.sim`` / ``virtualaxis.plant`` / ``virtualaxis.control`` (it imports nothing
from them): its own equations (docs/refaxis.md), its own integrator and its own controller discretisation.

Integrator: fixed step ``h = speed cycle / n_sub`` (31.25 us for both structures). Per step

1. the actuator's first-order lag is solved exactly for the held command (the step's mean effort is applied),
2. the LuGre bristle force ``sigma0 z + sigma1(v) dz/dt`` is evaluated from the state at the step's start
   and held over the step,
3. the smooth mechanics (masses, springs, dashpots, viscous friction, cogging, external force) advance by
   one classical RK4 step with those inputs held,
4. the bristle state ``z`` advances exactly (exponential solution of dz/dt = v - a z with the step's mean
   velocity frozen): the bristle equation is stiff during sliding (a = sigma0 |v| / g(v) ~ 1e5..1e6 1/s)
   and an explicit RK4 would diverge, so it is not put into the RK4 state.

The parameter vector ``p`` is indexed by the constants below (built by :func:`param_vector`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# ---- parameter vector layout -------------------------------------------------------------------------
PARAM_NAMES = (
    "structure",  # 0 = two_mass (motor side + table through the axial spring), 1 = rigid (one mass, force)
    "r_m_per_rad",  # lead / 2 pi [m/rad]
    "j_kg_m2",  # motor-side inertia (rotor + coupling + screw) [kg m^2]
    "bm_nm_s_per_rad",  # motor bearing viscous damping [N m s/rad]
    "m_kg",  # table mass carried rigidly (total table mass minus a resonant sub-mass) [kg]
    "k_mid_n_per_m",  # axial stiffness with the table at 0 (mid-stroke) [N/m]
    "ea_n",  # E A of the screw for the position dependence of the axial stiffness; 0: constant [N]
    "d0_m",  # distance fixed bearing -> nut with the table at 0 [m]
    "c_ax_n_s_per_m",  # dashpot parallel to the axial spring [N s/m]
    "gap_m",  # backlash, total [m]
    "mr_kg",  # resonant sub-mass on the table, 0 = none [kg]
    "kr_n_per_m",  # its spring [N/m]
    "cr_n_s_per_m",  # its dashpot [N s/m]
    "sigma0_n_per_m",  # LuGre bristle stiffness [N/m]
    "sigma1_n_s_per_m",  # LuGre bristle damping [N s/m]
    "fc_pos_n",  # Coulomb level for v > 0 [N]
    "fc_neg_n",  # Coulomb level for v < 0 [N]
    "fs_n",  # Stribeck excess at v = 0 [N]
    "vs_m_s",  # Stribeck velocity (Gaussian curve) [m/s]
    "fv_pos_n_s_per_m",  # viscous coefficient for v > 0 [N s/m]
    "fv_neg_n_s_per_m",  # viscous coefficient for v < 0 [N s/m]
    "f_off_n",  # constant force against +x (gravity share, cable drag) [N]
    "lead_ppm",  # cumulative lead deviation [ppm]
    "lead_amp_m",  # periodic lead error amplitude, A sin(theta + phi) [m]
    "lead_phase_rad",
    "cog_amp_nm",  # torque ripple amplitude, A sin(n theta + phi) [N m]
    "cog_order",  # periods per motor revolution
    "cog_phase_rad",
    "alpha_per_k",  # screw thermal expansion [1/K]
    "dtemp0_k",  # screw temperature rise at t = 0 [K]
    "rth_k_per_w",  # temperature rise per W of friction power (steady state) [K/W]
    "tau_th_s",  # thermal time constant [s]
    "tau_u_s",  # first-order force / torque loop time constant [s]
    "u_max",  # |torque| [N m] (two_mass) or |force| [N] (rigid) limit
    "kv_per_s",  # position-loop gain [1/s]
    "kff",  # velocity feed-forward weight 0..1
    "kp_speed",  # speed-loop gain [N m s/rad] (two_mass) or [N s/m] (rigid)
    "ti_speed_s",  # speed-loop integral time, 0 = P only [s]
    "ts_speed_s",  # speed-loop cycle [s]
    "n_speed",  # speed cycles per position cycle
    "n_sub",  # integration steps per speed cycle
    "enc_counts",  # motor encoder counts per revolution, 0 = ideal
    "enc_jitter_counts",  # encoder interpolation noise, 1 sigma [counts]
    "fb_quantum_m",  # rigid: linear-scale quantum of the loop feedback [m]
    "fb_noise_m",  # rigid: linear-scale noise of the loop feedback, 1 sigma [m]
    "delay_s",  # dead time of the position feedback (encoder / scale reading) [s]
    "est_samples",  # speed estimate: difference over 1 or 2 samples
    "ctrl_on",  # 1: closed loop; 0: effort = u_add only (open-loop tests)
    "t_pos_s",  # position-loop cycle [s]
    "fb_scale",  # two_mass only: 1 = position loop on the linear scale (full closed loop), 0 = motor encoder
    "out_delay_cycles",  # speed-loop output applied this many speed cycles after its sample (0, 1, 2)
)
P_STRUCTURE = 0
P_R_M_PER_RAD = 1
P_J_KG_M2 = 2
P_BM_NM_S_PER_RAD = 3
P_M_KG = 4
P_K_MID_N_PER_M = 5
P_EA_N = 6
P_D0_M = 7
P_C_AX_N_S_PER_M = 8
P_GAP_M = 9
P_MR_KG = 10
P_KR_N_PER_M = 11
P_CR_N_S_PER_M = 12
P_SIGMA0_N_PER_M = 13
P_SIGMA1_N_S_PER_M = 14
P_FC_POS_N = 15
P_FC_NEG_N = 16
P_FS_N = 17
P_VS_M_S = 18
P_FV_POS_N_S_PER_M = 19
P_FV_NEG_N_S_PER_M = 20
P_F_OFF_N = 21
P_LEAD_PPM = 22
P_LEAD_AMP_M = 23
P_LEAD_PHASE_RAD = 24
P_COG_AMP_NM = 25
P_COG_ORDER = 26
P_COG_PHASE_RAD = 27
P_ALPHA_PER_K = 28
P_DTEMP0_K = 29
P_RTH_K_PER_W = 30
P_TAU_TH_S = 31
P_TAU_U_S = 32
P_U_MAX = 33
P_KV_PER_S = 34
P_KFF = 35
P_KP_SPEED = 36
P_TI_SPEED_S = 37
P_TS_SPEED_S = 38
P_N_SPEED = 39
P_N_SUB = 40
P_ENC_COUNTS = 41
P_ENC_JITTER_COUNTS = 42
P_FB_QUANTUM_M = 43
P_FB_NOISE_M = 44
P_DELAY_S = 45
P_EST_SAMPLES = 46
P_CTRL_ON = 47
P_T_POS_S = 48
P_FB_SCALE = 49
P_OUT_DELAY_CYCLES = 50
N_PARAMS = len(PARAM_NAMES)
for _i, _name in enumerate(PARAM_NAMES):  # the constants above must follow the names' order
    assert globals()["P_" + _name.upper()] == _i, _name

# ---- recorded raw channels (one row per position-loop instant t_k, before the controller acts) ---------
C_X_TABLE = 0  # true table position [m]
C_THETA = 1  # true motor angle [rad]
C_FB = 2  # position feedback the position loop used at t_k [m] (delayed, quantised, noisy)
C_THETA_MEAS = 3  # motor encoder angle the drive read at t_k [rad] (delayed, quantised)
C_U_ACT = 4  # actuator effort at t_k (torque N m / force N) after the lag
C_U_CMD = 5  # effort command applied from t_k (held during [t_k, t_k+1) for the rigid 1 kHz loop): computed at
#             t_k, or at the sample out_delay_cycles speed cycles earlier
C_V_TABLE = 6  # true table velocity [m/s]
C_DTEMP = 7  # screw temperature rise [K]
C_F_SPRING = 8  # axial spring force [N]
N_CH = 9


def param_vector(values: dict) -> np.ndarray:
    """Build ``p`` from a dict of ``PARAM_NAMES`` entries (missing entries are 0; unknown names raise)."""
    p = np.zeros(N_PARAMS)
    for k, v in values.items():
        if k not in PARAM_NAMES:
            raise KeyError(f"unknown reference-axis parameter {k!r}")
        p[PARAM_NAMES.index(k)] = float(v)
    return p


@njit(cache=True)
def screw_position(p, theta, dtemp):
    """Nut position at the table coordinate for motor angle ``theta`` [m] and its derivative d/dtheta [m/rad].

    (d0 + r theta (1 + ppm 1e-6)) (1 + alpha dT) - d0 + A sin(theta + phi): the screw grows from the fixed
    bearing (d0 away from the nut at table 0), the lead deviates cumulatively and periodically per rev."""
    r = p[P_R_M_PER_RAD]
    eps = p[P_LEAD_PPM] * 1e-6
    th = 1.0 + p[P_ALPHA_PER_K] * dtemp
    a = p[P_LEAD_AMP_M]
    ph = p[P_LEAD_PHASE_RAD]
    pos = (p[P_D0_M] + r * theta * (1.0 + eps)) * th - p[P_D0_M] + a * math.sin(theta + ph)
    g = r * (1.0 + eps) * th + a * math.cos(theta + ph)
    return pos, g


@njit(cache=True)
def axial_stiffness(p, x):
    """Axial stiffness with the table at ``x`` [N/m]: other compliances in series with a screw length d0 + x."""
    k0 = p[P_K_MID_N_PER_M]
    ea = p[P_EA_N]
    if ea <= 0.0:
        return k0
    c_other = 1.0 / k0 - p[P_D0_M] / ea
    return 1.0 / (c_other + (p[P_D0_M] + x) / ea)


@njit(cache=True)
def spring_force(p, theta, omega, x, v, dtemp):
    """Axial force the screw puts on the table [N] and the lever d(nut)/d(theta) [m/rad] (two_mass only)."""
    pos, g = screw_position(p, theta, dtemp)
    d = pos - x
    dd = omega * g - v
    half = 0.5 * p[P_GAP_M]
    k = axial_stiffness(p, x)
    c = p[P_C_AX_N_S_PER_M]
    if d > half:
        f = k * (d - half) + c * dd
        if f < 0.0:
            f = 0.0
    elif d < -half:
        f = k * (d + half) + c * dd
        if f > 0.0:
            f = 0.0
    else:
        f = 0.0
    return f, g


@njit(cache=True)
def derivs(p, s0, s1, s2, s3, s4, s5, u, f_bristle, f_ext, dtemp):
    """Time derivative of the mechanical state (theta, omega, x, v, xr, vr) with inputs held.

    ``u``: motor torque [N m] (two_mass) or drive force [N] (rigid); ``f_bristle``: LuGre bristle force held
    over the step [N]; ``f_ext``: external force on the table along +x [N]."""
    v = s3
    fv = p[P_FV_POS_N_S_PER_M] if v >= 0.0 else p[P_FV_NEG_N_S_PER_M]
    f_fric = f_bristle + fv * v
    fr = 0.0
    if p[P_MR_KG] > 0.0:
        fr = p[P_KR_N_PER_M] * (s4 - s2) + p[P_CR_N_S_PER_M] * (s5 - s3)
    if p[P_STRUCTURE] == 0.0:
        fs, g = spring_force(p, s0, s1, s2, s3, dtemp)
        t_cog = p[P_COG_AMP_NM] * math.sin(p[P_COG_ORDER] * s0 + p[P_COG_PHASE_RAD])
        d1 = (u + t_cog - p[P_BM_NM_S_PER_RAD] * s1 - fs * g) / p[P_J_KG_M2]
        d3 = (fs - f_fric - p[P_F_OFF_N] + f_ext + fr) / p[P_M_KG]
        d0 = s1
    else:
        d0 = 0.0
        d1 = 0.0
        d3 = (u - f_fric - p[P_F_OFF_N] + f_ext + fr) / p[P_M_KG]
    d5 = 0.0
    if p[P_MR_KG] > 0.0:
        d5 = -fr / p[P_MR_KG]
    return d0, d1, s3, d3, s5, d5


@njit(cache=True)
def stribeck_level(p, v):
    """LuGre g(v): Coulomb level of the direction plus the Gaussian Stribeck excess [N] (> 0)."""
    fc = p[P_FC_POS_N] if v >= 0.0 else p[P_FC_NEG_N]
    g = fc
    if p[P_FS_N] > 0.0:
        g += p[P_FS_N] * math.exp(-((v / p[P_VS_M_S]) ** 2))
    return max(g, 1e-9)


@njit(cache=True)
def bristle_force(p, v, z):
    """LuGre force without the viscous term, sigma0 z + sigma1 exp(-(v/vs)^2) dz/dt [N]."""
    if p[P_SIGMA0_N_PER_M] <= 0.0:
        return 0.0
    g = stribeck_level(p, v)
    zdot = v - p[P_SIGMA0_N_PER_M] * abs(v) * z / g
    vs = p[P_VS_M_S] if p[P_VS_M_S] > 0.0 else 1e-3
    return p[P_SIGMA0_N_PER_M] * z + p[P_SIGMA1_N_S_PER_M] * math.exp(-((v / vs) ** 2)) * zdot


@njit(cache=True)
def bristle_update(p, z, v, h):
    """Exact solution of dz/dt = v - sigma0 |v| z / g(v) over ``h`` with ``v`` frozen."""
    if p[P_SIGMA0_N_PER_M] <= 0.0:
        return 0.0
    g = stribeck_level(p, v)
    a = p[P_SIGMA0_N_PER_M] * abs(v) / g
    if a * h < 1e-9:
        return z + v * h
    zss = v / a
    return zss + (z - zss) * math.exp(-a * h)


@njit(cache=True)
def mech_step(p, s, u, f_bristle, f_ext, dtemp, h):
    """One RK4 step of the mechanics in place (``s``: theta, omega, x, v, xr, vr)."""
    a0, a1, a2, a3, a4, a5 = derivs(p, s[0], s[1], s[2], s[3], s[4], s[5], u, f_bristle, f_ext, dtemp)
    hh = 0.5 * h
    b0, b1, b2, b3, b4, b5 = derivs(p, s[0] + hh * a0, s[1] + hh * a1, s[2] + hh * a2, s[3] + hh * a3,
                                    s[4] + hh * a4, s[5] + hh * a5, u, f_bristle, f_ext, dtemp)
    c0, c1, c2, c3, c4, c5 = derivs(p, s[0] + hh * b0, s[1] + hh * b1, s[2] + hh * b2, s[3] + hh * b3,
                                    s[4] + hh * b4, s[5] + hh * b5, u, f_bristle, f_ext, dtemp)
    d0, d1, d2, d3, d4, d5 = derivs(p, s[0] + h * c0, s[1] + h * c1, s[2] + h * c2, s[3] + h * c3,
                                    s[4] + h * c4, s[5] + h * c5, u, f_bristle, f_ext, dtemp)
    w = h / 6.0
    s[0] += w * (a0 + 2 * b0 + 2 * c0 + d0)
    s[1] += w * (a1 + 2 * b1 + 2 * c1 + d1)
    s[2] += w * (a2 + 2 * b2 + 2 * c2 + d2)
    s[3] += w * (a3 + 2 * b3 + 2 * c3 + d3)
    s[4] += w * (a4 + 2 * b4 + 2 * c4 + d4)
    s[5] += w * (a5 + 2 * b5 + 2 * c5 + d5)


@njit(cache=True)
def open_loop(p, s0, u, h):
    """Mechanics alone under an effort sequence ``u`` (one value per step ``h``), friction state from rest.

    Returns the state after every step, shape (len(u), 7): theta, omega, x, v, xr, vr, z. For tests (FRF,
    energy, breakaway)."""
    s = s0.copy()
    out = np.empty((u.shape[0], 7))
    z = 0.0
    for i in range(u.shape[0]):
        fb = bristle_force(p, s[3], z)
        v_old = s[3]
        mech_step(p, s, u[i], fb, 0.0, p[P_DTEMP0_K], h)
        z = bristle_update(p, z, 0.5 * (v_old + s[3]), h)
        for j in range(6):
            out[i, j] = s[j]
        out[i, 6] = z
    return out


@njit(cache=True)
def _hist_read(hist, n_hist, n_written, h, t_back, fallback):
    """Value of a signal ``t_back`` seconds before the newest entry, linear interpolation on the ring."""
    m = t_back / h
    i0 = int(math.floor(m))
    fr = m - i0
    if i0 + 1 >= n_written or i0 + 1 >= n_hist:
        return fallback
    a = hist[(n_written - 1 - i0) % n_hist]
    b = hist[(n_written - 2 - i0) % n_hist]
    return a + fr * (b - a)


@njit(cache=True)
def run_axis(p, x_cmd, u_add, f_ext, enc_noise, fb_noise, s_init, z_init, integ_init, u_init):
    """Closed-loop run over the command ``x_cmd`` (one sample per position cycle) -> raw channels (n, N_CH).

    ``u_add``: effort added to the controller output per position cycle (open loop when ctrl_on = 0);
    ``f_ext``: external force per position cycle [N]; ``enc_noise``: standard-normal draws, one per speed
    cycle (encoder interpolation jitter); ``fb_noise``: standard-normal draws per position cycle (scale).
    """
    n = x_cmd.shape[0]
    out = np.zeros((n, N_CH))
    two_mass = p[P_STRUCTURE] == 0.0
    r = p[P_R_M_PER_RAD]
    n_speed = int(p[P_N_SPEED])
    n_sub = int(p[P_N_SUB])
    ts = p[P_TS_SPEED_S]
    tpos = p[P_T_POS_S]
    h = ts / n_sub
    kp = p[P_KP_SPEED]
    ki_ts = kp * ts / p[P_TI_SPEED_S] if p[P_TI_SPEED_S] > 0.0 else 0.0
    umax = p[P_U_MAX]
    tau = p[P_TAU_U_S]
    e_lag = math.exp(-h / tau) if tau > 0.0 else 0.0
    avg_lag = (tau / h) * (1.0 - e_lag) if tau > 0.0 else 0.0
    q_enc = 2.0 * math.pi / p[P_ENC_COUNTS] if p[P_ENC_COUNTS] > 0.0 else 0.0
    q_fb = p[P_FB_QUANTUM_M]
    delay = p[P_DELAY_S]
    est = int(p[P_EST_SAMPLES])
    n_hist = 8192
    hist_th = np.zeros(n_hist)  # motor angle after every integration step (encoder dead time)
    hist_x = np.zeros(n_hist)  # table position after every integration step (scale dead time)
    scale_fb = (not two_mass) or p[P_FB_SCALE] != 0.0
    delay_enc = delay if (two_mass and not scale_fb) else 0.0
    delay_scale = delay if scale_fb else 0.0

    s = s_init.copy()
    z = z_init
    integ = integ_init
    u_act = u_init
    u_cmd = u_init
    u_app = u_init  # the effort the actuator is commanded (u_cmd delayed by out_delay_cycles)
    n_delay = int(p[P_OUT_DELAY_CYCLES])
    held = np.full(3, u_init)  # held[i]: the command computed i + 1 speed cycles ago
    dtemp = p[P_DTEMP0_K]
    g_th = p[P_RTH_K_PER_W]
    tau_th = p[P_TAU_TH_S]
    # feedback history (rigid loop: measured scale of the last samples)
    fb_prev1 = s[2]
    fb_prev2 = s[2]
    theta_meas_prev = s[0]
    hist_th[0] = s[0]
    hist_x[0] = s[2]
    n_written = 1
    enc_i = 0
    for k in range(n):
        # ---- sample at t_k ------------------------------------------------------------------------
        theta_meas = 0.0
        if two_mass:
            th_true = _hist_read(hist_th, n_hist, n_written, h, delay_enc, hist_th[0]) if delay_enc > 0.0 else s[0]
            th = th_true + p[P_ENC_JITTER_COUNTS] * q_enc * enc_noise[enc_i]
            if q_enc > 0.0:
                th = math.floor(th / q_enc + 0.5) * q_enc
            fb = r * th
            theta_meas = th
        if scale_fb:
            x_true = _hist_read(hist_x, n_hist, n_written, h, delay_scale, hist_x[0]) if delay_scale > 0.0 else s[2]
            xm = x_true + p[P_FB_NOISE_M] * fb_noise[k]
            if q_fb > 0.0:
                xm = math.floor(xm / q_fb + 0.5) * q_fb
            fb = xm
        pos_fs = 0.0
        if two_mass:
            pos_fs, _g = spring_force(p, s[0], s[1], s[2], s[3], dtemp)
        out[k, C_X_TABLE] = s[2]
        out[k, C_THETA] = s[0]
        out[k, C_FB] = fb
        out[k, C_THETA_MEAS] = theta_meas
        out[k, C_U_ACT] = u_act
        out[k, C_V_TABLE] = s[3]
        out[k, C_DTEMP] = dtemp
        out[k, C_F_SPRING] = pos_fs
        # ---- position loop (P + velocity feed-forward from the command's backward difference) ---------
        vff = (x_cmd[k] - x_cmd[k - 1]) / tpos if k > 0 else 0.0
        v_set = p[P_KV_PER_S] * (x_cmd[k] - fb) + p[P_KFF] * vff
        for j in range(n_speed):
            # ---- speed loop ---------------------------------------------------------------------------
            if two_mass:
                if j > 0:
                    th_true = (_hist_read(hist_th, n_hist, n_written, h, delay_enc, hist_th[0])
                               if delay_enc > 0.0 else s[0])
                    th = th_true + p[P_ENC_JITTER_COUNTS] * q_enc * enc_noise[enc_i]
                    if q_enc > 0.0:
                        th = math.floor(th / q_enc + 0.5) * q_enc
                w_est = (th - theta_meas_prev) / ts
                theta_meas_prev = th
                err = v_set / r - w_est
            else:
                if est == 2:
                    v_est = (fb - fb_prev2) / (2.0 * ts)  # two-sample difference
                else:
                    v_est = (fb - fb_prev1) / ts
                fb_prev2 = fb_prev1
                fb_prev1 = fb
                err = v_set - v_est
            enc_i += 1
            if enc_i >= enc_noise.shape[0]:
                enc_i = 0
            if p[P_CTRL_ON] != 0.0:
                integ_new = integ + ki_ts * err
                u_try = kp * err + integ_new + u_add[k]
                if u_try > umax:
                    u_cmd = umax
                    if ki_ts * err < 0.0:
                        integ = integ_new  # anti-windup: integrate only towards the range
                elif u_try < -umax:
                    u_cmd = -umax
                    if ki_ts * err > 0.0:
                        integ = integ_new
                else:
                    u_cmd = u_try
                    integ = integ_new
            else:
                u_cmd = u_add[k]
            if n_delay > 0:
                # computed from this sample, applied n_delay speed cycles later
                u_app = held[n_delay - 1]
                for i in range(n_delay - 1, 0, -1):
                    held[i] = held[i - 1]
                held[0] = u_cmd
            else:
                u_app = u_cmd
            if j == 0:
                out[k, C_U_CMD] = u_app
            # ---- plant over one speed cycle ----------------------------------------------------------
            for _i in range(n_sub):
                if tau > 0.0:
                    u_mean = u_app + (u_act - u_app) * avg_lag
                    u_act = u_app + (u_act - u_app) * e_lag
                else:
                    u_mean = u_app
                    u_act = u_app
                fbr = bristle_force(p, s[3], z)
                v_old = s[3]
                mech_step(p, s, u_mean, fbr, f_ext[k], dtemp, h)
                v_mid = 0.5 * (v_old + s[3])
                z = bristle_update(p, z, v_mid, h)
                if g_th > 0.0 or dtemp != 0.0:
                    fv = p[P_FV_POS_N_S_PER_M] if v_mid >= 0.0 else p[P_FV_NEG_N_S_PER_M]
                    power = abs((fbr + fv * v_mid) * v_mid)
                    dtemp += h * (g_th * power - dtemp) / tau_th
                hist_th[n_written % n_hist] = s[0]
                hist_x[n_written % n_hist] = s[2]
                n_written += 1
    return out, s, z, integ, u_act
