"""The compiled multi-rate kernel: position loop (P + feed-forward) -> speed loop (PI) -> current loops (PI)
-> inverter -> PMSM (dq) -> lumped mechanics with backlash and stick/slip friction -> sensors.

Each loop runs at its own sample time and holds its output between samples, as a digital drive does. The
current-loop voltage is applied one PWM period after it is computed (computation delay). The mechanics are
advanced with exact zero-order-hold matrices per contact/stick mode (see :mod:`virtualaxis.plant.discrete`).

Everything here is allocation-free: the caller owns every array (see :mod:`virtualaxis.sim.layout`).

Speed (benchmarks/bench_plant.py; BENCHMARKS.md "Plant kernel speed-up"): :func:`run_cycles` is compiled
without the NRT (``_nrt=False``): it allocates nothing, and with the NRT every array handed to an inlined helper
cost atomic reference-count calls in the hot loop (the largest single cost). Parameters are read into locals
once per call; the mechanical step of the six-body model (12 states) runs as ``<4 x double>`` fused
multiply-adds on transposed mode tables (:func:`_zoh_12`; any other size takes :func:`_zoh_generic`); the
cogging and periodic lead-error sines advance by a rotation recurrence re-seeded from ``math.sin``/``math.cos``
at every position-loop sample (:func:`sin_cos_step`). None of this changes the model: results agree with the
plain loops to round-off.
"""

from __future__ import annotations

import math

from llvmlite import ir
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)
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
    P_BRAKE_N,
    P_COG_A,
    P_COG_N,
    P_COG_PH,
    P_DEAD_FRAC,
    P_DEAD_SENSOR,
    P_DECOUP,
    P_DELTA,
    P_EST2,
    P_EXP_D,
    P_EXP_Q,
    P_FB,
    P_FC_NEG,
    P_FC_POS,
    P_FF_SETPOINT,
    P_FORCE_ACT,
    P_FORCE_LAG,
    P_FRIC,
    P_FS,
    P_FV,
    P_FV_NEG,
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
    P_NDEAD0,
    P_NDOF,
    P_NGRID,
    P_NOISE_I,
    P_NOISE_POS,
    P_NPOS,
    P_NSPD,
    P_NSUB,
    P_NUT_OFF,
    P_OUT_DELAY,
    P_PP,
    P_PSI,
    P_QENC,
    P_QSCALE,
    P_R,
    P_RS,
    P_SCREW,
    P_SPD_FILT,
    P_STOP_C,
    P_STOP_HI,
    P_STOP_K,
    P_STOP_KH,
    P_STOP_LO,
    P_STOP_TRAVEL,
    P_SVPWM,
    P_SVSUB,
    P_TABLE,
    P_TH_ALPHA,
    P_TH_R,
    P_TH_TAU,
    P_TPOS,
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
    S_FF_VALID,
    S_ID,
    S_ILIM,
    S_INT_D,
    S_INT_Q,
    S_INT_W,
    S_IQ,
    S_IQ_REF,
    S_MODE,
    S_OUT_HELD1,
    S_OUT_HELD2,
    S_POS_FB,
    S_RING,
    S_RIPPLE,
    S_SPD_INIT,
    S_STUCK,
    S_T,
    S_TEMP,
    S_TFF,
    S_THETA_PREV,
    S_THETA_PREV2,
    S_TORQUE,
    S_UD_APP,
    S_UD_NEXT,
    S_UQ_APP,
    S_UQ_NEXT,
    S_VFF_PREV,
    S_VSAT,
    S_W_MEAS,
    S_W_REF,
    Z0,
)

SQRT3 = math.sqrt(3.0)


@njit(cache=True, fastmath=True)
def blend_tables(pr, st, adt, bdt, krow, crow, wat, wbt, wk, wc):
    """Interpolate the mode tables linearly at the present nut position (once per position cycle).

    The tables come transposed, ``adt[g, m, c, r] = Ad[g, m, r, c]`` and ``bdt[g, m, c, r] = Bd[g, m, r, c]``,
    so that the step ``z <- Ad z + Bd u`` reads each column contiguously (vectorisable across rows).
    """
    ngrid = int(pr[P_NGRID])
    if ngrid == 1:
        for m in range(adt.shape[1]):
            for c in range(adt.shape[2]):
                for r in range(adt.shape[3]):
                    wat[m, c, r] = adt[0, m, c, r]
            for c in range(bdt.shape[2]):
                for r in range(bdt.shape[3]):
                    wbt[m, c, r] = bdt[0, m, c, r]
        for m in range(krow.shape[1]):
            for c in range(krow.shape[2]):
                wk[m, c] = krow[0, m, c]
                wc[m, c] = crow[0, m, c]
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
    for m in range(adt.shape[1]):
        for c in range(adt.shape[2]):
            for r in range(adt.shape[3]):
                wat[m, c, r] = w0 * adt[i, m, c, r] + w * adt[i + 1, m, c, r]
        for c in range(bdt.shape[2]):
            for r in range(bdt.shape[3]):
                wbt[m, c, r] = w0 * bdt[i, m, c, r] + w * bdt[i + 1, m, c, r]
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
def _dot_state(vec, z, offset, n):
    """sum_i vec[i] z[offset + i]: motor angle (offset 0) or speed (offset n) when the motor is not one body.
    Only called in branches that are rare in the hot loop: passing arrays to an inlined function costs
    reference-count calls there."""
    s = 0.0
    for i in range(n):
        s += vec[i] * z[offset + i]
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
def _delayed_reading(ring, ri, n0, frac, col):
    """The ring's column ``col`` (0 motor angle, 1 table position) ``n0 + frac`` current cycles before the newest
    entry ``ri``, interpolated linearly between the two entries around it (``frac`` = 0: the entry itself)."""
    a = ring[(ri - n0) % RING_SIZE, col]
    if frac == 0.0:
        return a
    return a + frac * (ring[(ri - n0 - 1) % RING_SIZE, col] - a)


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


@njit(cache=True)
def stribeck_cut_ratio(stribeck_n, coulomb_min_n, exponent):
    """Velocity ratio |v|/v_s beyond which F_s exp(-(|v|/v_s)^delta) < 2^-54 F_c, i.e. less than half an ulp of
    the Coulomb force, so that F_c + (Stribeck term) == F_c exactly and the kernel may skip the ``exp``.
    ``inf`` (never skip) when there is no Coulomb force to absorb the term. Computed from ``pr`` at every call,
    so parameters changed between calls are honoured."""
    if stribeck_n <= 0.0 or coulomb_min_n <= 0.0 or exponent <= 0.0:
        return math.inf
    x = 54.0 * math.log(2.0) + math.log(stribeck_n / coulomb_min_n) + 1.0  # one unit of margin in the exponent
    return max(x, 0.0) ** (1.0 / exponent)


SIN_STEP_MAX_RAD = 0.2  # largest angle increment the rotation recurrence of :func:`sin_cos_step` takes


@njit(cache=True, fastmath=True, inline="always")
def sin_cos_step(x, x_prev, s_prev, c_prev, exact):
    """(sin x, cos x) from the values at ``x_prev`` by one rotation through ``d = x - x_prev``, with sin d and
    cos d - 1 from their Taylor series (truncation < 1e-17 for |d| <= 0.2 rad). Falls back to ``math.sin`` /
    ``math.cos`` when ``exact`` is set or the increment is larger. The kernel re-seeds with ``exact`` at every
    position-loop sample, so at most one cycle of recurrence round-off (~1e-14) accumulates."""
    d = x - x_prev
    if exact or not abs(d) <= SIN_STEP_MAX_RAD:
        return math.sin(x), math.cos(x)
    d2 = d * d
    sd = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0 * (1.0 - d2 / 110.0)))))
    cm1 = -0.5 * d2 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0 * (1.0 - d2 / 90.0
                                                                                  * (1.0 - d2 / 132.0)))))
    return s_prev + (s_prev * cm1 + c_prev * sd), c_prev + (c_prev * cm1 - s_prev * sd)


@njit(cache=True, fastmath=True, inline="always")
def _zoh_generic(at, bt, m, z, ztmp, s, u0, u1, u2, u3):
    """``z <- Ad z + Bd u`` for any state size, with the transposed tables of :func:`blend_tables`."""
    for r in range(s):
        ztmp[r] = bt[m, 0, r] * u0 + bt[m, 1, r] * u1 + bt[m, 2, r] * u2 + bt[m, 3, r] * u3
    for c in range(s):
        zc = z[c]
        for r in range(s):  # contiguous column of Ad: vectorises
            ztmp[r] += at[m, c, r] * zc
    for r in range(s):
        z[r] = ztmp[r]


@intrinsic
def _zoh_12(typingctx, at, bt, m, z, u0, u1, u2, u3):
    """``z <- Ad z + Bd u`` for 12 states (six bodies) in ``<4 x double>`` fused multiply-adds: three vectors of
    four rows, columns of the transposed tables ``at[m, c, :]`` (4, 12, 12) and ``bt[m, k, :]`` (4, 4, 12), which
    must be C-contiguous; ``z`` must be contiguous (12,). Numba turns LLVM's SLP vectoriser off by default
    (NUMBA_SLP_VECTORIZE=0), so the vector code is written here. Four independent partial sums per row group
    keep the dependency chains short; the same products as :func:`_zoh_generic`, added in a different order
    (round-off)."""
    for arr in (at, bt, z):
        if not (isinstance(arr, types.Array) and arr.dtype == types.float64 and arr.layout in "CA"):
            return None
    if at.layout != "C" or bt.layout != "C" or at.ndim != 3 or bt.ndim != 3 or z.ndim != 1:
        return None
    sig = types.void(at, bt, m, z, u0, u1, u2, u3)

    def codegen(context, builder, signature, args):
        f64, i32, i64 = ir.DoubleType(), ir.IntType(32), ir.IntType(64)
        v4 = ir.VectorType(f64, 4)
        undef4 = ir.Constant(v4, ir.Undefined)
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v4, [v4, v4, v4]), "llvm.fma.v4f64")
        at_data = context.make_array(signature.args[0])(context, builder, args[0]).data
        bt_data = context.make_array(signature.args[1])(context, builder, args[1]).data
        z_data = context.make_array(signature.args[3])(context, builder, args[3]).data
        m64 = context.cast(builder, args[2], signature.args[2], types.int64)
        us = args[4:]

        def vptr(base, idx):
            return builder.bitcast(builder.gep(base, [idx]), v4.as_pointer())

        def lane(vec, i):
            return builder.shuffle_vector(vec, undef4, ir.Constant(ir.VectorType(i32, 4), [i] * 4))

        def broadcast(x):
            return lane(builder.insert_element(undef4, x, ir.Constant(i32, 0)), 0)

        a0 = builder.mul(m64, ir.Constant(i64, 144))
        b0 = builder.mul(m64, ir.Constant(i64, 48))
        zv = [builder.load(vptr(z_data, ir.Constant(i64, 4 * g)), align=8) for g in range(3)]
        part = [[None] * 4 for _ in range(3)]

        def mac(slot, g, base, offset, xb):
            col = builder.load(vptr(base, builder.add(offset, ir.Constant(i64, 4 * g))), align=8)
            prev = part[g][slot]
            part[g][slot] = builder.fmul(col, xb) if prev is None else builder.call(fma, [col, xb, prev])

        for c in range(12):
            zb = lane(zv[c // 4], c % 4)
            for g in range(3):
                mac(c // 4, g, at_data, builder.add(a0, ir.Constant(i64, 12 * c)), zb)
        for k in (0, 2, 1, 3):  # actuator and external force first: friction and contact come from this step
            ub = broadcast(us[k])
            for g in range(3):
                mac(3, g, bt_data, builder.add(b0, ir.Constant(i64, 12 * k)), ub)
        for g in range(3):
            p = part[g]
            acc = builder.fadd(builder.fadd(p[0], p[1]), builder.fadd(p[2], p[3]))
            builder.store(acc, vptr(z_data, ir.Constant(i64, 4 * g)), align=8)
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, fastmath=True, inline="always")
def _mech_step(mp, z, at, bt, wk, wc, gtab, avec, ztmp, actuator, f_ext, was_stuck, d_dir, temp, lead_sc):
    """One mechanical step with backlash mode and stick/slip friction (Karnopp-type switch).

    Stuck: the table rows are frozen (no creep); the friction force is whatever holds the table, until the
    net force exceeds the break-away force F_c + F_s. Sliding: the friction force follows the Stribeck curve,
    and a velocity sign change within a step sticks the table (no chatter).

    ``mp`` holds the mechanical parameters (see :func:`run_cycles`); ``lead_sc`` = (angle, sin, cos, exact) of
    the periodic lead error's phase at the previous step (see :func:`sin_cos_step`). Returns the new (stuck,
    direction, temperature rise, friction force, contact force, contact-gap flag, lead_sc).
    """
    (n, tb, sb, has_contact, bl, half, kc, lead_k, lead_a, lead_ph, th_alpha, nut_off, fric, fc_pos, fc_neg, fs,
     vs, dl, fv, strib_cut, th_gain, th_r, fv_neg) = mp
    s = 2 * n
    # --- contact (backlash) mode
    cg = 0
    ucontact = 0.0
    cforce = 0.0
    if has_contact:
        # kinematic offset of the nut: lead error (cumulative, periodic) and thermal growth [m]
        kin = 0.0
        if sb >= 0:
            theta = z[sb]
            kin = lead_k * theta
            if lead_a != 0.0:
                xl = theta + lead_ph
                sl, cl = sin_cos_step(xl, lead_sc[0], lead_sc[1], lead_sc[2], lead_sc[3])
                lead_sc = (xl, sl, cl, False)
                kin += lead_a * sl
            if th_alpha != 0.0:
                kin += th_alpha * temp * (nut_off + z[tb])
        delta = kin
        for i in range(n):
            delta += avec[i] * z[i]
        if not bl:
            ucontact = kc * kin
            cforce = kc * delta
        else:
            if delta > half:
                ucontact = kc * (kin - half)
                cforce = kc * (delta - half)
            elif delta < -half:
                ucontact = kc * (kin + half)
                cforce = kc * (delta + half)
            else:
                cg = 1
    # --- friction
    stuck = 0
    ffric = 0.0
    v_old = z[n + tb]
    if fric:
        if was_stuck:
            fnet = gtab[0] * actuator + gtab[2] * f_ext + gtab[3] * ucontact
            for i in range(n):
                fnet -= wk[cg, i] * z[i] + wc[cg, i] * z[n + i]
            if fnet >= 0.0:
                brk = fc_pos + fs
            else:
                brk = fc_neg + fs
            if abs(fnet) <= brk:
                stuck = 1
                ffric = -fnet
            else:
                d = 1.0 if fnet > 0.0 else -1.0
                d_dir = d
                ffric = -d * brk
        else:
            v = v_old
            if v > 0.0:
                d = 1.0
            elif v < 0.0:
                d = -1.0
            else:
                d = d_dir
            if d > 0.0:
                fc = fc_pos
                fvd = fv
            else:
                fc = fc_neg
                fvd = fv_neg  # direction-dependent viscous coefficient (== fv unless configured)
            av = abs(v)
            strib = 0.0
            if fs != 0.0:
                ratio = av / vs
                # beyond strib_cut the Stribeck term is below half an ulp of F_c: F_c + it == F_c exactly
                if ratio < strib_cut:
                    if dl == 1.0:
                        strib = fs * math.exp(-ratio)
                    elif dl == 2.0:
                        strib = fs * math.exp(-ratio * ratio)
                    else:
                        strib = fs * math.exp(-(ratio**dl))
            ffric = -d * (fc + strib) - fvd * v
    u1 = 0.0 if stuck else ffric
    mode = cg + 2 * stuck
    if s == 12:
        _zoh_12(at, bt, mode, z, actuator, u1, f_ext, ucontact)
    else:
        _zoh_generic(at, bt, mode, z, ztmp, s, actuator, u1, f_ext, ucontact)
    if fric:
        if stuck:
            was_stuck = True
            z[n + tb] = 0.0
        else:
            v_new = z[n + tb]
            d = d_dir
            if v_old != 0.0:
                d = 1.0 if v_old > 0.0 else -1.0
            if v_new * d <= 0.0:
                # velocity reversed within the step: the table sticks
                z[n + tb] = 0.0
                was_stuck = True
            else:
                was_stuck = False
                d_dir = d
    elif was_stuck:  # neither friction nor a brake holds the table now
        was_stuck = False
    # thermal growth of the screw, driven by friction power
    if th_alpha != 0.0:
        p = abs(ffric * z[n + tb]) if not stuck else 0.0
        temp += th_gain * (th_r * p - temp)
    return was_stuck, d_dir, temp, ffric, cforce, cg, lead_sc


@njit(cache=True, fastmath=True, inline="always")
def end_stop_force(x, v, lo, hi, k, c, travel, kh):
    """Force of the hard end stops on the table [N]. Beyond ``lo`` / ``hi`` [m] the table first compresses a
    damped buffer (spring ``k`` [N/m], damper ``c`` [N s/m]) over ``travel`` [m]; the rigid stop behind it adds
    the stiffness ``kh`` [N/m]. The contact only pushes (it never pulls the table back into the stop)."""
    if x > hi:
        d = x - hi
        f = -k * d - c * v
        if d > travel:
            f -= kh * (d - travel)
        return f if f < 0.0 else 0.0
    if x < lo:
        d = lo - x
        f = k * d - c * v
        if d > travel:
            f += kh * (d - travel)
        return f if f > 0.0 else 0.0
    return 0.0


# _nrt=False: no reference counting (and no allocation possible) in the hot loop; every array is owned by the
# caller for the duration of the call.
@njit(cache=True, fastmath=True, _nrt=False, nogil=True)
def run_cycles(st, pr, adt, bdt, krow, crow, gtab, avec, mvec, ring, wat, wbt, wk, wc, ztmp,
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
    theta_prev2 = st[S_THETA_PREV2]
    vsat = st[S_VSAT]
    t_now = st[S_T]
    ri = int(st[S_RING])
    # mechanical parameters (read once per call: the hot loop stores into st and ring, which the compiler must
    # assume may alias pr) and states held in locals
    # a holding brake on the table is a Coulomb friction of its holding force on top of the axis' own (the
    # table sticks while the net force is within it); without friction only the brake's force acts
    fric_on = pr[P_FRIC] != 0.0
    brake_n = pr[P_BRAKE_N]
    fc_pos = (pr[P_FC_POS] if fric_on else 0.0) + brake_n
    fc_neg = (pr[P_FC_NEG] if fric_on else 0.0) + brake_n
    fs = pr[P_FS] if fric_on else 0.0
    fv = pr[P_FV] if fric_on else 0.0
    fv_neg = pr[P_FV_NEG] if fric_on else 0.0
    mp = (n, tb, int(pr[P_SCREW]), pr[P_HAS_CONTACT] != 0.0, pr[P_BL] != 0.0, pr[P_BL_HALF], pr[P_KC],
          pr[P_LEAD_PPM] * 1e-6 * pr[P_R], pr[P_LEAD_PER_A], pr[P_LEAD_PER_PH], pr[P_TH_ALPHA], pr[P_NUT_OFF],
          fric_on or brake_n != 0.0, fc_pos, fc_neg, fs, pr[P_VS], pr[P_DELTA], fv,
          stribeck_cut_ratio(fs, min(fc_pos, fc_neg), pr[P_DELTA]),
          pr[P_HM] / pr[P_TH_TAU] if pr[P_TH_ALPHA] != 0.0 else 0.0, pr[P_TH_R], fv_neg)
    was_stuck = st[S_STUCK] != 0.0
    d_dir = st[S_DIR]
    temp = st[S_TEMP]
    ffric = st[S_F_FRIC]
    cforce = st[S_CONTACT_F]
    cgap = int(st[S_CONTACT_MODE])
    x_cog, s_cog, c_cog = 0.0, 0.0, 1.0
    midx = int(pr[P_MOTOR_IDX])
    qenc, qscale, r_lead = pr[P_QENC], pr[P_QSCALE], pr[P_R]
    fb_motor = pr[P_FB] == 0.0 and r_lead > 0.0
    # drive / axis options (control/options.py); the defaults take the branches of the kernel before them
    est2 = pr[P_EST2] != 0.0
    spd_filt = pr[P_SPD_FILT]
    ndead0 = int(pr[P_NDEAD0])
    dead_frac = pr[P_DEAD_FRAC]
    # sensors.dead_time_scope = "feedback_sensor": the feedback sensor's reading is delayed everywhere, i.e. also in
    # the speed loop when it differentiates that sensor (force actuator: always; pmsm: motor-encoder feedback) and
    # in the recorded channel of that sensor
    dly_sensor = pr[P_DEAD_SENSOR] != 0.0 and (ndead0 > 0 or dead_frac > 0.0)
    dly_speed = dly_sensor and (force_act or fb_motor)
    ff_setpoint = pr[P_FF_SETPOINT] != 0.0
    tpos = pr[P_TPOS]
    # control.output_delay_s: the speed loop's output is applied out_delay speed cycles after its samples
    out_delay = int(pr[P_OUT_DELAY])
    out_held1, out_held2 = st[S_OUT_HELD1], st[S_OUT_HELD2]
    stop_lo, stop_hi, stop_k, stop_c = pr[P_STOP_LO], pr[P_STOP_HI], pr[P_STOP_K], pr[P_STOP_C]
    stop_travel, stop_kh = pr[P_STOP_TRAVEL], pr[P_STOP_KH]
    for j in range(ncyc):
        blend_tables(pr, st, adt, bdt, krow, crow, wat, wbt, wk, wc)
        # the sin recurrences restart from exact values at every position-loop sample
        cog_exact = True
        lead_sc = (0.0, 0.0, 1.0, True)
        mode = int(st[S_MODE])
        enabled = st[S_ENABLED] != 0.0
        st[S_F_EXT] = f_ext[j]
        cmd_prev = st[S_CMD_POS]
        st[S_CMD_POS] = cmd_pos[j]
        # ---- position loop sample
        st[S_RING] = ri
        if dly_sensor:
            # the feedback sensor's reading D = (ndead0 + dead_frac) current cycles old, interpolated
            if fb_motor:
                fb = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 0), qenc) * r_lead
            else:
                fb = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 1), qscale)
        else:
            fb = _feedback_position(pr, st, ring)
        st[S_POS_FB] = fb
        fe = cmd_pos[j] - fb
        st[S_FE] = fe
        tff = 0.0
        if enabled and mode == MODE_POSITION:
            if ff_setpoint:
                # CSP drive: feed-forward from the set-point differences, held for the cycle; the first set-point
                # in position control has no predecessor and takes the caller's values
                if st[S_FF_VALID] != 0.0:
                    vff = (cmd_pos[j] - cmd_prev) / tpos
                    aff = (vff - st[S_VFF_PREV]) / tpos
                else:
                    vff = cmd_vel[j]
                    aff = cmd_acc[j]
                st[S_VFF_PREV] = vff
                st[S_FF_VALID] = 1.0
            else:
                vff = cmd_vel[j]
                aff = cmd_acc[j]
            wref = g * (pr[P_KV] * fe + pr[P_KFF] * vff)
            tff = pr[P_KTFF] * pr[P_JREF] * g * aff
        elif enabled and mode == MODE_VELOCITY:
            wref = g * cmd_aux[j]
            st[S_FF_VALID] = 0.0
        else:
            wref = 0.0
            st[S_FF_VALID] = 0.0
        wref = clamp(wref, pr[P_WLIM])
        st[S_W_REF] = wref
        st[S_TFF] = tff
        # ---- record the sampling instant
        x_tab = zview[tb]
        out[j, O_T] = t_now
        out[j, O_POS_CMD] = cmd_pos[j]
        out[j, O_POS_MEAS] = quantise(x_tab + pr[P_NOISE_POS] * noise[j, 0], pr[P_QSCALE])
        out[j, O_POS_FB] = fb
        th_m = zview[midx] if midx >= 0 else _dot_state(mvec, zview, 0, n)
        out[j, O_MOTOR_POS] = quantise(th_m, pr[P_QENC])
        if dly_sensor:
            # the recorded channel of the feedback sensor is its delayed reading (what the drive read)
            if fb_motor:
                out[j, O_MOTOR_POS] = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 0), qenc)
            else:
                out[j, O_POS_MEAS] = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 1)
                                              + pr[P_NOISE_POS] * noise[j, 0], qscale)
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
        out[j, O_FRICTION] = ffric
        out[j, O_STUCK] = 1.0 if was_stuck else 0.0
        out[j, O_CONTACT_F] = cforce
        out[j, O_MOTOR_SPEED] = zview[n + midx] if midx >= 0 else _dot_state(mvec, zview, n, n)
        out[j, O_TABLE_TRUE] = x_tab
        out[j, O_TEMP] = temp
        out[j, O_AIRGAP] = torque_act
        vsat_any = 0.0
        ilim_any = 0.0
        energy = 0.0
        # ---- current cycles within this position cycle
        kspd = 0
        for _k in range(npos):
            # motor angle [rad] and speed [rad/s] at the start of this current cycle
            if midx >= 0:
                th_m = zview[midx]
                wm = zview[n + midx]
            else:
                th_m = _dot_state(mvec, zview, 0, n)
                wm = _dot_state(mvec, zview, n, n)
            if kspd == 0:
                # the quantity whose difference the speed loop measures: motor angle [rad] (pmsm) or position [m]
                if dly_speed:
                    if not force_act:
                        coord = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 0), qenc)
                    elif fb_motor:
                        coord = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 0), qenc) * r_lead
                    else:
                        coord = quantise(_delayed_reading(ring, ri, ndead0, dead_frac, 1), qscale)
                elif not force_act:
                    coord = quantise(th_m, qenc)
                elif fb_motor:
                    coord = quantise(th_m, qenc) * r_lead
                else:
                    coord = quantise(zview[tb], qscale)
                if st[S_SPD_INIT] == 0.0:
                    theta_prev = coord
                    theta_prev2 = coord
                    st[S_SPD_INIT] = 1.0
                if est2:
                    # two-sample difference (q[k] - q[k-2]) / 2T
                    w_raw = (coord - theta_prev2) / (2.0 * tspd)
                    theta_prev2 = theta_prev
                else:
                    w_raw = (coord - theta_prev) / tspd
                theta_prev = coord
                if spd_filt > 0.0:
                    # first-order low-pass, step-invariant: w_f += (1 - exp(-T/tau)) (w - w_f)
                    w_meas += spd_filt * (w_raw - w_meas)
                else:
                    w_meas = w_raw
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
                    tref = cmd_aux[j]
                    wlim = pr[P_WLIM]
                    if wlim > 0.0:
                        # speed limitation in torque control: the speed controller's P part, set to the
                        # limit, caps the torque (and brakes when the load drives the axis past it)
                        if tref > 0.0:
                            tref = min(tref, kpw * (wlim - w_meas))
                        elif tref < 0.0:
                            tref = max(tref, kpw * (-wlim - w_meas))
                    tref = clamp(tref, lim)
                    if abs(cmd_aux[j]) > lim > 0.0:
                        ilim_any = 1.0
                    iq_ref = tref if force_act else tref / kt
                    int_w = 0.0
                else:
                    iq_ref = 0.0
                    int_w = 0.0
                if out_delay > 0:
                    # computed from this sample, applied one (two) speed cycle(s) later
                    computed = iq_ref
                    if out_delay == 1:
                        iq_ref = out_held1
                    else:
                        iq_ref = out_held2
                        out_held2 = out_held1
                    out_held1 = computed
            kspd += 1
            if kspd == nspd:
                kspd = 0
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
                        th_e = pp * th_m
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
                    xc = cog_n * th_m + cog_ph
                    s_cog, c_cog = sin_cos_step(xc, x_cog, s_cog, c_cog, cog_exact)
                    x_cog = xc
                    cog_exact = False
                    torque += cog_a * s_cog
                actuator = torque
            torque_act = actuator
            fx = f_ext[j]
            for _ in range(nsub):
                fxs = fx
                if stop_k != 0.0:
                    fxs += end_stop_force(zview[tb], zview[n + tb], stop_lo, stop_hi, stop_k, stop_c,
                                          stop_travel, stop_kh)
                was_stuck, d_dir, temp, ffric, cforce, cgap, lead_sc = _mech_step(
                    mp, zview, wat, wbt, wk, wc, gtab, avec, ztmp, actuator, fxs, was_stuck, d_dir, temp, lead_sc)
            t_now += hc
            # feedback ring buffer (motor angle, table position) at the current-loop rate
            ri += 1
            if ri >= RING_SIZE:
                ri = 0
            ring[ri, 0] = zview[midx] if midx >= 0 else _dot_state(mvec, zview, 0, n)
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
    st[S_THETA_PREV2] = theta_prev2
    st[S_OUT_HELD1], st[S_OUT_HELD2] = out_held1, out_held2
    st[S_VSAT] = vsat
    st[S_T] = t_now
    st[S_RING] = ri
    st[S_STUCK] = 1.0 if was_stuck else 0.0
    st[S_DIR] = d_dir
    st[S_TEMP] = temp
    st[S_F_FRIC] = ffric
    st[S_CONTACT_F] = cforce
    st[S_CONTACT_MODE] = cgap
    return ncyc
