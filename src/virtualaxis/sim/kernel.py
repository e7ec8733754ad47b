"""The compiled multi-rate kernel: position loop (P + feed-forward) -> speed loop (PI) -> current loops (PI)
-> inverter -> PMSM (dq) -> lumped mechanics with backlash and stick/slip friction -> sensors.

Each loop runs at its own sample time and holds its output between samples, as a digital drive does. The
current-loop voltage is applied one PWM period after it is computed (computation delay). The mechanics are
advanced with exact zero-order-hold matrices per contact/stick mode (see :mod:`virtualaxis.plant.discrete`).

Everything here is allocation-free: the caller owns every array (see :mod:`virtualaxis.sim.layout`).
"""

from __future__ import annotations

import math

from numba import njit

from virtualaxis.control.loops import clamp, pi_step, quantise
from virtualaxis.sim.layout import (
    MODE_POSITION,
    MODE_TORQUE,
    MODE_VELOCITY,
    O_AIRGAP,
    O_CONTACT_F,
    O_CURRENT_D,
    O_CURRENT_Q,
    O_FOLLOWING,
    O_FORCE_DRIVE,
    O_FORCE_EXT,
    O_FRICTION,
    O_ILIM,
    O_MOTOR_POS,
    O_MOTOR_SPEED,
    O_POS_CMD,
    O_POS_FB,
    O_POS_MEAS,
    O_POWER,
    O_RIPPLE,
    O_STUCK,
    O_T,
    O_TABLE_TRUE,
    O_TEMP,
    O_TORQUE,
    O_VEL,
    O_VOLT_D,
    O_VOLT_Q,
    O_VSAT,
    P_BL,
    P_BL_HALF,
    P_COG_A,
    P_COG_N,
    P_COG_PH,
    P_DECOUP,
    P_DELTA,
    P_EXP_D,
    P_EXP_Q,
    P_FB,
    P_FC_NEG,
    P_FC_POS,
    P_FORCE_ACT,
    P_FORCE_LAG,
    P_FRIC,
    P_FS,
    P_FV,
    P_G,
    P_GI_I,
    P_GI_W,
    P_GRID_LO,
    P_GRID_STEP,
    P_HAS_CONTACT,
    P_HC,
    P_HM,
    P_ILIM,
    P_INV_RS,
    P_JREF,
    P_KC,
    P_KFF,
    P_KPI,
    P_KPW,
    P_KT,
    P_KTFF,
    P_KV,
    P_LD,
    P_LEAD_PER_A,
    P_LEAD_PER_PH,
    P_LEAD_PPM,
    P_LQ,
    P_MOTOR_IDX,
    P_NDEAD,
    P_NDOF,
    P_NGRID,
    P_NOISE_I,
    P_NOISE_POS,
    P_NPOS,
    P_NSPD,
    P_NSUB,
    P_NUT_OFF,
    P_PP,
    P_PSI,
    P_QENC,
    P_QSCALE,
    P_R,
    P_RS,
    P_SCREW,
    P_SVPWM,
    P_SVSUB,
    P_TABLE,
    P_TH_ALPHA,
    P_TH_R,
    P_TH_TAU,
    P_VDC,
    P_VMAX,
    P_VMAX2,
    P_VS,
    P_WLIM,
    RING_SIZE,
    S_CMD_POS,
    S_CONTACT_F,
    S_CONTACT_MODE,
    S_DIR,
    S_ENABLED,
    S_F_ACT,
    S_F_EXT,
    S_F_FRIC,
    S_FE,
    S_ID,
    S_ILIM,
    S_INT_D,
    S_INT_Q,
    S_INT_W,
    S_IQ,
    S_IQ_REF,
    S_MODE,
    S_POS_FB,
    S_RING,
    S_RIPPLE,
    S_SPD_INIT,
    S_STUCK,
    S_T,
    S_TEMP,
    S_TFF,
    S_THETA_PREV,
    S_TORQUE,
    S_UD_APP,
    S_UD_NEXT,
    S_UQ_APP,
    S_UQ_NEXT,
    S_VSAT,
    S_W_MEAS,
    S_W_REF,
    Z0,
)

SQRT3 = math.sqrt(3.0)


@njit(cache=True, fastmath=True)
def blend_tables(pr, st, ad, bd, krow, crow, wad, wbd, wk, wc):
    """Interpolate the mode tables linearly at the present nut position (once per position cycle)."""
    ngrid = int(pr[P_NGRID])
    if ngrid == 1:
        for m in range(ad.shape[1]):
            for r in range(ad.shape[2]):
                for c in range(ad.shape[3]):
                    wad[m, r, c] = ad[0, m, r, c]
                for c in range(bd.shape[3]):
                    wbd[m, r, c] = bd[0, m, r, c]
        wk[:] = krow[0]
        wc[:] = crow[0]
        return
    nut = pr[P_NUT_OFF] + st[Z0 + int(pr[P_TABLE])]
    f = (nut - pr[P_GRID_LO]) / pr[P_GRID_STEP]
    if f < 0.0:
        f = 0.0
    if f > ngrid - 1.0:
        f = ngrid - 1.0
    i = int(f)
    if i >= ngrid - 1:
        i = ngrid - 2
    w = f - i
    w0 = 1.0 - w
    for m in range(ad.shape[1]):
        for r in range(ad.shape[2]):
            for c in range(ad.shape[3]):
                wad[m, r, c] = w0 * ad[i, m, r, c] + w * ad[i + 1, m, r, c]
            for c in range(bd.shape[3]):
                wbd[m, r, c] = w0 * bd[i, m, r, c] + w * bd[i + 1, m, r, c]
    for m in range(krow.shape[1]):
        for c in range(krow.shape[2]):
            wk[m, c] = w0 * krow[i, m, c] + w * krow[i + 1, m, c]
            wc[m, c] = w0 * crow[i, m, c] + w * crow[i + 1, m, c]


@njit(cache=True, fastmath=True, inline="always")
def motor_angle(pr, st, mvec):
    """True motor (drive) angle [rad] from the mechanical state."""
    idx = int(pr[P_MOTOR_IDX])
    if idx >= 0:
        return st[Z0 + idx]
    n = int(pr[P_NDOF])
    s = 0.0
    for i in range(n):
        s += mvec[i] * st[Z0 + i]
    return s


@njit(cache=True, fastmath=True, inline="always")
def motor_speed(pr, st, mvec):
    idx = int(pr[P_MOTOR_IDX])
    n = int(pr[P_NDOF])
    if idx >= 0:
        return st[Z0 + n + idx]
    s = 0.0
    for i in range(n):
        s += mvec[i] * st[Z0 + n + i]
    return s


@njit(cache=True, fastmath=True, inline="always")
def _feedback_position(pr, st, ring):
    """Position feedback of the position loop at the table [m], delayed by the measurement dead time."""
    nd = int(pr[P_NDEAD])
    idx = int(st[S_RING])
    j = (idx - nd) % RING_SIZE
    if pr[P_FB] == 0.0:
        r = pr[P_R]
        if r > 0.0:
            return quantise(ring[j, 0], pr[P_QENC]) * r
        return quantise(ring[j, 1], pr[P_QSCALE])
    return quantise(ring[j, 1], pr[P_QSCALE])


@njit(cache=True, fastmath=True, inline="always")
def _speed_sample_coordinate(pr, st, mvec):
    """The quantity whose difference the speed loop measures: motor angle [rad] (pmsm) or position [m]."""
    if pr[P_FORCE_ACT] == 0.0:
        return quantise(motor_angle(pr, st, mvec), pr[P_QENC])
    if pr[P_FB] == 0.0 and pr[P_R] > 0.0:
        return quantise(motor_angle(pr, st, mvec), pr[P_QENC]) * pr[P_R]
    return quantise(st[Z0 + int(pr[P_TABLE])], pr[P_QSCALE])


@njit(cache=True, fastmath=True, inline="always")
def _kinematic_offset(pr, st):
    """Offset of the nut's kinematic position: lead error (cumulative, periodic) and thermal growth [m]."""
    sb = int(pr[P_SCREW])
    if sb < 0:
        return 0.0
    theta = st[Z0 + sb]
    off = pr[P_LEAD_PPM] * 1e-6 * pr[P_R] * theta
    if pr[P_LEAD_PER_A] != 0.0:
        off += pr[P_LEAD_PER_A] * math.sin(theta + pr[P_LEAD_PER_PH])
    if pr[P_TH_ALPHA] != 0.0:
        off += pr[P_TH_ALPHA] * st[S_TEMP] * (pr[P_NUT_OFF] + st[Z0 + int(pr[P_TABLE])])
    return off


@njit(cache=True, fastmath=True, inline="always")
def _electrical_averaged(pp, ld, lq, psi, inv_rs, exp_d, exp_q, idd, iqq, ud, uq, wm):
    """Advance i_d, i_q over one PWM period with the averaged inverter voltage (exponential integrator with
    the cross-coupling held). Returns (i_d, i_q, period-average air-gap torque)."""
    we = pp * wm
    ed = ud + we * lq * iqq
    eq = uq - we * (ld * idd + psi)
    id1 = idd * exp_d + (1.0 - exp_d) * ed * inv_rs
    iq1 = iqq * exp_q + (1.0 - exp_q) * eq * inv_rs
    # average torque over the period (trapezoid on the currents)
    id_m = 0.5 * (idd + id1)
    iq_m = 0.5 * (iqq + iq1)
    return id1, iq1, 1.5 * pp * (psi * iq_m + (ld - lq) * id_m * iq_m)


@njit(cache=True, fastmath=True)
def _electrical_svpwm(pr, st, ud, uq, wm, theta_e0, h):
    """Switching-level inverter: SVPWM sector, dwell times and centre-aligned switching of the six switches
    (seed 000 Fig. 6); the dq currents are integrated through each switching segment. Returns the
    period-average air-gap torque."""
    vdc = pr[P_VDC]
    we = pr[P_PP] * wm
    # reference in the stationary frame at the middle of the period
    th_mid = theta_e0 + 0.5 * we * h
    c = math.cos(th_mid)
    s = math.sin(th_mid)
    ua = ud * c - uq * s
    ub = ud * s + uq * c
    # sector and dwell times
    ang = math.atan2(ub, ua)
    if ang < 0.0:
        ang += 2.0 * math.pi
    sector = int(ang / (math.pi / 3.0))
    if sector > 5:
        sector = 5
    mag = math.sqrt(ua * ua + ub * ub)
    rel = ang - sector * math.pi / 3.0
    t1 = SQRT3 * mag / vdc * math.sin(math.pi / 3.0 - rel) * h
    t2 = SQRT3 * mag / vdc * math.sin(rel) * h
    if t1 + t2 > h:
        k = h / (t1 + t2)
        t1 *= k
        t2 *= k
    t0 = h - t1 - t2
    # switching states of the two adjacent active vectors (Sa, Sb, Sc) for each sector
    # V1=100 V2=110 V3=010 V4=011 V5=001 V6=101
    va = sector
    vb = (sector + 1) % 6
    # centre-aligned: V0 t0/4, Va t1/2, Vb t2/2, V7 t0/2, Vb t2/2, Va t1/2, V0 t0/4
    nsub = int(pr[P_SVSUB])
    torque_int = 0.0
    t_now = 0.0
    iq_int = 0.0
    iq2_int = 0.0
    for seg in range(7):
        if seg == 0 or seg == 6:
            dur = 0.25 * t0
            vec = -1
        elif seg == 1 or seg == 5:
            dur = 0.5 * t1
            vec = va
        elif seg == 2 or seg == 4:
            dur = 0.5 * t2
            vec = vb
        else:
            dur = 0.5 * t0
            vec = -2
        if dur <= 0.0:
            continue
        # phase-to-neutral voltages from the switch states
        sa, sb, sc = 0.0, 0.0, 0.0
        if vec == -2:
            sa, sb, sc = 1.0, 1.0, 1.0
        elif vec >= 0:
            if vec == 0:
                sa, sb, sc = 1.0, 0.0, 0.0
            elif vec == 1:
                sa, sb, sc = 1.0, 1.0, 0.0
            elif vec == 2:
                sa, sb, sc = 0.0, 1.0, 0.0
            elif vec == 3:
                sa, sb, sc = 0.0, 1.0, 1.0
            elif vec == 4:
                sa, sb, sc = 0.0, 0.0, 1.0
            else:
                sa, sb, sc = 1.0, 0.0, 1.0
        van = vdc / 3.0 * (2.0 * sa - sb - sc)
        vbn = vdc / 3.0 * (2.0 * sb - sa - sc)
        valpha = van
        vbeta = (van + 2.0 * vbn) / SQRT3
        dt = dur / nsub
        for _ in range(nsub):
            th = theta_e0 + we * (t_now + 0.5 * dt)
            cc = math.cos(th)
            ss = math.sin(th)
            vd = valpha * cc + vbeta * ss
            vq = -valpha * ss + vbeta * cc
            idd = st[S_ID]
            iqq = st[S_IQ]
            did = (vd - pr[P_RS] * idd + we * pr[P_LQ] * iqq) / pr[P_LD]
            diq = (vq - pr[P_RS] * iqq - we * (pr[P_LD] * idd + pr[P_PSI])) / pr[P_LQ]
            # Heun step
            id1 = idd + dt * did
            iq1 = iqq + dt * diq
            did2 = (vd - pr[P_RS] * id1 + we * pr[P_LQ] * iq1) / pr[P_LD]
            diq2 = (vq - pr[P_RS] * iq1 - we * (pr[P_LD] * id1 + pr[P_PSI])) / pr[P_LQ]
            st[S_ID] = idd + 0.5 * dt * (did + did2)
            st[S_IQ] = iqq + 0.5 * dt * (diq + diq2)
            id_m = 0.5 * (idd + st[S_ID])
            iq_m = 0.5 * (iqq + st[S_IQ])
            torque_int += dt * 1.5 * pr[P_PP] * (pr[P_PSI] * iq_m + (pr[P_LD] - pr[P_LQ]) * id_m * iq_m)
            iq_int += dt * iq_m
            iq2_int += dt * iq_m * iq_m
            t_now += dt
    mean = iq_int / h
    var = iq2_int / h - mean * mean
    if var > 0.0:
        st[S_RIPPLE] += var * h
    return torque_int / h


@njit(cache=True, fastmath=True, inline="always")
def _mech_step(pr, st, z, wad, wbd, wk, wc, gtab, avec, ztmp, u, actuator):
    """One mechanical step with backlash mode and stick/slip friction (Karnopp-type switch).

    Stuck: the table rows are frozen (no creep); the friction force is whatever holds the table, until the
    net force exceeds the break-away force F_c + F_s. Sliding: the friction force follows the Stribeck curve,
    and a velocity sign change within a step sticks the table (no chatter).
    """
    n = int(pr[P_NDOF])
    s = 2 * n
    tb = int(pr[P_TABLE])
    # --- contact (backlash) mode
    cg = 0
    ucontact = 0.0
    cforce = 0.0
    if pr[P_HAS_CONTACT] != 0.0:
        kin = _kinematic_offset(pr, st)
        delta = kin
        ddelta = 0.0
        for i in range(n):
            delta += avec[i] * st[Z0 + i]
            ddelta += avec[i] * st[Z0 + n + i]
        kc = pr[P_KC]
        if pr[P_BL] == 0.0:
            ucontact = kc * kin
            cforce = kc * delta
        else:
            half = pr[P_BL_HALF]
            if delta > half:
                ucontact = kc * (kin - half)
                cforce = kc * (delta - half)
            elif delta < -half:
                ucontact = kc * (kin + half)
                cforce = kc * (delta + half)
            else:
                cg = 1
    st[S_CONTACT_F] = cforce
    st[S_CONTACT_MODE] = cg
    u[0] = actuator
    u[2] = st[S_F_EXT]
    u[3] = ucontact
    # --- friction
    stuck = 0
    ffric = 0.0
    v_old = st[Z0 + n + tb]
    if pr[P_FRIC] != 0.0:
        if st[S_STUCK] != 0.0:
            fnet = gtab[0] * u[0] + gtab[2] * u[2] + gtab[3] * u[3]
            for i in range(n):
                fnet -= wk[cg, i] * st[Z0 + i] + wc[cg, i] * st[Z0 + n + i]
            if fnet >= 0.0:
                brk = pr[P_FC_POS] + pr[P_FS]
            else:
                brk = pr[P_FC_NEG] + pr[P_FS]
            if abs(fnet) <= brk:
                stuck = 1
                ffric = -fnet
            else:
                d = 1.0 if fnet > 0.0 else -1.0
                st[S_DIR] = d
                ffric = -d * brk
        else:
            v = v_old
            if v > 0.0:
                d = 1.0
            elif v < 0.0:
                d = -1.0
            else:
                d = st[S_DIR]
            fc = pr[P_FC_POS] if d > 0.0 else pr[P_FC_NEG]
            av = abs(v)
            strib = 0.0
            if pr[P_FS] != 0.0:
                ratio = av / pr[P_VS]
                dl = pr[P_DELTA]
                if dl == 1.0:
                    strib = pr[P_FS] * math.exp(-ratio)
                elif dl == 2.0:
                    strib = pr[P_FS] * math.exp(-ratio * ratio)
                else:
                    strib = pr[P_FS] * math.exp(-(ratio**dl))
            ffric = -d * (fc + strib) - pr[P_FV] * v
    u[1] = 0.0 if stuck else ffric
    st[S_F_FRIC] = ffric
    mode = cg + 2 * stuck
    u0, u1, u2, u3 = u[0], u[1], u[2], u[3]
    for r in range(s):
        acc = wbd[mode, r, 0] * u0 + wbd[mode, r, 1] * u1 + wbd[mode, r, 2] * u2 + wbd[mode, r, 3] * u3
        for c in range(s):
            acc += wad[mode, r, c] * z[c]
        ztmp[r] = acc
    for r in range(s):
        z[r] = ztmp[r]
    if pr[P_FRIC] != 0.0:
        if stuck:
            st[S_STUCK] = 1.0
            st[Z0 + n + tb] = 0.0
        else:
            v_new = st[Z0 + n + tb]
            d = st[S_DIR]
            if v_old != 0.0:
                d = 1.0 if v_old > 0.0 else -1.0
            if v_new * d <= 0.0:
                # velocity reversed within the step: the table sticks
                st[Z0 + n + tb] = 0.0
                st[S_STUCK] = 1.0
            else:
                st[S_STUCK] = 0.0
                st[S_DIR] = d
    # thermal growth of the screw, driven by friction power
    if pr[P_TH_ALPHA] != 0.0:
        p = abs(ffric * st[Z0 + n + tb]) if not stuck else 0.0
        st[S_TEMP] += pr[P_HM] / pr[P_TH_TAU] * (pr[P_TH_R] * p - st[S_TEMP])


@njit(cache=True, fastmath=True)
def run_cycles(st, pr, ad, bd, krow, crow, gtab, avec, mvec, ring, wad, wbd, wk, wc, ztmp, u,
               cmd_pos, cmd_vel, cmd_acc, cmd_aux, f_ext, noise, out):
    """Run ``len(cmd_pos)`` position-loop cycles. Row ``j`` of ``out`` holds the signals at the start of
    cycle ``j`` (the position-loop sampling instant), before the cycle is simulated.

    ``cmd_aux`` is the velocity set-point [m/s] in velocity mode or the torque [N m] / force [N] set-point in
    torque mode. ``noise`` holds standard-normal samples (scale, current) per cycle. The hot electrical and
    controller states live in locals for the whole call and are written back to ``st`` at the end.
    """
    ncyc = cmd_pos.shape[0]
    hc = pr[P_HC]
    npos = int(pr[P_NPOS])
    nspd = int(pr[P_NSPD])
    nsub = int(pr[P_NSUB])
    n = int(pr[P_NDOF])
    tb = int(pr[P_TABLE])
    g = pr[P_G]
    force_act = pr[P_FORCE_ACT] != 0.0
    svpwm = pr[P_SVPWM] != 0.0
    tspd = hc * nspd
    zview = st[Z0:Z0 + 2 * n]
    # parameters used every current cycle
    pp, ld, lq, psi = pr[P_PP], pr[P_LD], pr[P_LQ], pr[P_PSI]
    inv_rs, exp_d, exp_q = pr[P_INV_RS], pr[P_EXP_D], pr[P_EXP_Q]
    kpi, gii, kpw, giw = pr[P_KPI], pr[P_GI_I], pr[P_KPW], pr[P_GI_W]
    kt, vmax, vmax2 = pr[P_KT], pr[P_VMAX], pr[P_VMAX2]
    decoup = pr[P_DECOUP] != 0.0
    cog_a, cog_n, cog_ph = pr[P_COG_A], pr[P_COG_N], pr[P_COG_PH]
    lim = pr[P_ILIM] * (kt if not force_act else 1.0)
    lag = pr[P_FORCE_LAG]
    lag_f = 1.0 - math.exp(-hc / lag) if lag > 0.0 else 1.0
    # states held in locals
    i_d, i_q = st[S_ID], st[S_IQ]
    ud_app, uq_app, ud_next, uq_next = st[S_UD_APP], st[S_UQ_APP], st[S_UD_NEXT], st[S_UQ_NEXT]
    int_d, int_q, int_w = st[S_INT_D], st[S_INT_Q], st[S_INT_W]
    iq_ref, f_act, torque_act = st[S_IQ_REF], st[S_F_ACT], st[S_TORQUE]
    theta_prev, w_meas = st[S_THETA_PREV], st[S_W_MEAS]
    vsat = st[S_VSAT]
    t_now = st[S_T]
    ri = int(st[S_RING])
    for j in range(ncyc):
        blend_tables(pr, st, ad, bd, krow, crow, wad, wbd, wk, wc)
        mode = int(st[S_MODE])
        enabled = st[S_ENABLED] != 0.0
        st[S_F_EXT] = f_ext[j]
        st[S_CMD_POS] = cmd_pos[j]
        # ---- position loop sample
        st[S_RING] = ri
        fb = _feedback_position(pr, st, ring)
        st[S_POS_FB] = fb
        fe = cmd_pos[j] - fb
        st[S_FE] = fe
        tff = 0.0
        if enabled and mode == MODE_POSITION:
            wref = g * (pr[P_KV] * fe + pr[P_KFF] * cmd_vel[j])
            tff = pr[P_KTFF] * pr[P_JREF] * g * cmd_acc[j]
        elif enabled and mode == MODE_VELOCITY:
            wref = g * cmd_aux[j]
        else:
            wref = 0.0
        wref = clamp(wref, pr[P_WLIM])
        st[S_W_REF] = wref
        st[S_TFF] = tff
        # ---- record the sampling instant
        x_tab = zview[tb]
        out[j, O_T] = t_now
        out[j, O_POS_CMD] = cmd_pos[j]
        out[j, O_POS_MEAS] = quantise(x_tab + pr[P_NOISE_POS] * noise[j, 0], pr[P_QSCALE])
        out[j, O_POS_FB] = fb
        out[j, O_MOTOR_POS] = quantise(motor_angle(pr, st, mvec), pr[P_QENC])
        out[j, O_VEL] = zview[n + tb]
        if force_act:
            out[j, O_TORQUE] = f_act
            out[j, O_CURRENT_Q] = 0.0
            out[j, O_FORCE_DRIVE] = f_act
        else:
            iq_meas = i_q + pr[P_NOISE_I] * noise[j, 1]
            out[j, O_TORQUE] = kt * iq_meas
            out[j, O_CURRENT_Q] = iq_meas
            out[j, O_FORCE_DRIVE] = 0.0
        out[j, O_FORCE_EXT] = f_ext[j]
        out[j, O_FOLLOWING] = fe
        out[j, O_CURRENT_D] = i_d
        out[j, O_VOLT_Q] = uq_app
        out[j, O_VOLT_D] = ud_app
        out[j, O_FRICTION] = st[S_F_FRIC]
        out[j, O_STUCK] = st[S_STUCK]
        out[j, O_CONTACT_F] = st[S_CONTACT_F]
        out[j, O_MOTOR_SPEED] = motor_speed(pr, st, mvec)
        out[j, O_TABLE_TRUE] = x_tab
        out[j, O_TEMP] = st[S_TEMP]
        out[j, O_AIRGAP] = torque_act
        vsat_any = 0.0
        ilim_any = 0.0
        energy = 0.0
        # ---- current cycles within this position cycle
        for k in range(npos):
            if k % nspd == 0:
                coord = _speed_sample_coordinate(pr, st, mvec)
                if st[S_SPD_INIT] == 0.0:
                    theta_prev = coord
                    st[S_SPD_INIT] = 1.0
                w_meas = (coord - theta_prev) / tspd
                theta_prev = coord
                if enabled and mode != MODE_TORQUE:
                    ew = wref - w_meas
                    tref, int_w, _sat = pi_step(ew, int_w, kpw, giw, 0.0)
                    tref += tff
                    if lim > 0.0 and abs(tref) > lim:
                        tref = clamp(tref, lim)
                        # anti-windup at the current limit: undo the last integration when pushing further
                        if (tref > 0.0) == (ew > 0.0):
                            int_w -= ew * giw
                        ilim_any = 1.0
                    iq_ref = tref if force_act else tref / kt
                elif enabled and mode == MODE_TORQUE:
                    tref = clamp(cmd_aux[j], lim)
                    if tref != cmd_aux[j]:
                        ilim_any = 1.0
                    iq_ref = tref if force_act else tref / kt
                    int_w = 0.0
                else:
                    iq_ref = 0.0
                    int_w = 0.0
            wm = motor_speed(pr, st, mvec)
            if force_act:
                # force actuator: first-order force loop
                if enabled:
                    f_act += (iq_ref - f_act) * lag_f
                else:
                    f_act = 0.0
                actuator = f_act
            else:
                # ---- current loop (one-period computation delay)
                ud_app = ud_next
                uq_app = uq_next
                if enabled:
                    we = pp * wm
                    ffd = 0.0
                    ffq = 0.0
                    if decoup:
                        ffd = -we * lq * i_q
                        ffq = we * (ld * i_d + psi)
                    ud, intd, _s1 = pi_step(-i_d, int_d, kpi, gii, 0.0)
                    uq, intq, _s2 = pi_step(iq_ref - i_q, int_q, kpi, gii, 0.0)
                    ud += ffd
                    uq += ffq
                    mag2 = ud * ud + uq * uq
                    if mag2 > vmax2:
                        # voltage limit; anti-windup: hold the integrators while saturated
                        sc = vmax / math.sqrt(mag2)
                        ud *= sc
                        uq *= sc
                        vsat_any = 1.0
                        vsat = 1.0
                    else:
                        vsat = 0.0
                        int_d = intd
                        int_q = intq
                    ud_next = ud
                    uq_next = uq
                else:
                    ud_next = 0.0
                    uq_next = 0.0
                    int_d = 0.0
                    int_q = 0.0
                if enabled:
                    id0 = i_d
                    iq0 = i_q
                    if svpwm:
                        st[S_ID] = i_d
                        st[S_IQ] = i_q
                        th_e = pp * motor_angle(pr, st, mvec)
                        torque = _electrical_svpwm(pr, st, ud_app, uq_app, wm, th_e, hc)
                        i_d = st[S_ID]
                        i_q = st[S_IQ]
                    else:
                        i_d, i_q, torque = _electrical_averaged(pp, ld, lq, psi, inv_rs, exp_d, exp_q, i_d, i_q,
                                                                ud_app, uq_app, wm)
                    energy += 1.5 * (ud_app * 0.5 * (id0 + i_d) + uq_app * 0.5 * (iq0 + i_q)) * hc
                else:
                    i_d = 0.0
                    i_q = 0.0
                    torque = 0.0
                if cog_a != 0.0:
                    torque += cog_a * math.sin(cog_n * motor_angle(pr, st, mvec) + cog_ph)
                actuator = torque
            torque_act = actuator
            for _ in range(nsub):
                _mech_step(pr, st, zview, wad, wbd, wk, wc, gtab, avec, ztmp, u, actuator)
            t_now += hc
            # feedback ring buffer (motor angle, table position) at the current-loop rate
            ri += 1
            if ri >= RING_SIZE:
                ri = 0
            ring[ri, 0] = motor_angle(pr, st, mvec)
            ring[ri, 1] = zview[tb]
        out[j, O_VSAT] = vsat_any
        out[j, O_ILIM] = ilim_any
        st[S_ILIM] = ilim_any
        out[j, O_POWER] = energy / (hc * npos)
        out[j, O_RIPPLE] = math.sqrt(st[S_RIPPLE] / (hc * npos))
        st[S_RIPPLE] = 0.0
    # write the local states back
    st[S_ID], st[S_IQ] = i_d, i_q
    st[S_UD_APP], st[S_UQ_APP], st[S_UD_NEXT], st[S_UQ_NEXT] = ud_app, uq_app, ud_next, uq_next
    st[S_INT_D], st[S_INT_Q], st[S_INT_W] = int_d, int_q, int_w
    st[S_IQ_REF], st[S_F_ACT], st[S_TORQUE] = iq_ref, f_act, torque_act
    st[S_THETA_PREV], st[S_W_MEAS] = theta_prev, w_meas
    st[S_VSAT] = vsat
    st[S_T] = t_now
    st[S_RING] = ri
    return ncyc
