"""Reference integration of the same equations with scipy's ``solve_ivp`` (tight tolerances, event-located
switching), written independently of the compiled kernel to cross-check its discretisation.

Between current-loop samples the continuous plant (dq currents with the held inverter voltage, lumped mechanics
with the nut-position-dependent stiffness interpolated on the same grid, backlash dead zone, friction) is
integrated by ``solve_ivp``; stick/slip and backlash contact changes are located with events. The digital
controllers (position P + feed-forward, speed PI, current PI with decoupling and voltage limit, quantised and
delayed feedback) are evaluated at their sample instants exactly as a drive does, with the drive / axis options of
``control/options.py`` written out from their definitions (speed-estimator form and filter, set-point feed-forward,
dead time on the feedback sensor interpolated between current-cycle states, direction-dependent viscous friction).
pmsm actuators only.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from virtualaxis.config import AxisConfig
from virtualaxis.plant.discrete import discretise
from virtualaxis.plant.mechanics import (
    build_mechanics,
    damping_matrix,
    nut_position_range_m,
    reflected_inertia_kg_m2,
    structural_damping_coefficient,
)


def _q(v: float, quantum: float) -> float:
    return quantum * math.floor(v / quantum) if quantum > 0 else v


class ReferenceAxis:
    def __init__(self, cfg: AxisConfig, rtol: float = 1e-9, atol: float = 1e-12, method: str = "DOP853"):
        if cfg.actuator.kind != "pmsm" or cfg.inverter.model != "averaged":
            raise ValueError("the reference integrator covers pmsm axes with the averaged inverter")
        self.cfg = cfg
        self.rtol, self.atol, self.method = rtol, atol, method
        lo, hi = nut_position_range_m(cfg)
        npts = cfg.simulation.position_grid_points
        self.grid = np.array([lo]) if hi <= lo else np.linspace(lo, hi, max(npts, 2))
        b = structural_damping_coefficient(cfg)
        self.mats = []
        for x in self.grid:
            mech = build_mechanics(cfg, x)
            minv = np.linalg.inv(mech.mass_matrix())
            self.mats.append((
                minv @ mech.stiffness_matrix(False), minv @ damping_matrix(mech, b, False),  # without contact
            ))
        self.mech = build_mechanics(cfg, self.grid[0])
        self.minv = np.linalg.inv(self.mech.mass_matrix())
        self.n = self.mech.n
        self.tb = self.mech.table_body
        self.a = self.mech.incidence(self.mech.contact) if self.mech.contact is not None else np.zeros(self.n)
        self.kc = self.mech.contact.stiffness if self.mech.contact is not None else 0.0
        self.cc = b * self.kc
        self.g = self.mech.input_matrix()
        self.mvec = self.mech.motor_angle_vector
        self.sb = self.mech.screw_body
        m = cfg.motor
        self.psi = m.psi_wb
        self.kt = m.kt_nm_per_a
        self.r = cfg.mechanics.lead_m / (2 * math.pi)
        self.dm = discretise(cfg, cfg.control.current_cycle_s)  # only for the grid it shares with the kernel

    # -------------------------------------------------------------------------------------------- plant
    def _matrices(self, x_tab: float):
        nut = self.cfg.axis.nut_offset_m + x_tab
        if len(self.grid) == 1:
            return self.mats[0]
        f = np.clip((nut - self.grid[0]) / (self.grid[1] - self.grid[0]), 0, len(self.grid) - 1)
        i = min(int(f), len(self.grid) - 2)
        w = f - i
        (k0, c0), (k1, c1) = self.mats[i], self.mats[i + 1]
        return (1 - w) * k0 + w * k1, (1 - w) * c0 + w * c1

    def _kin(self, q, temp):
        if self.sb is None:
            return 0.0
        e = self.cfg.effects
        th = q[self.sb]
        off = e.lead_error_ppm * 1e-6 * self.r * th
        off += e.lead_error_periodic_m * math.sin(th + e.lead_error_periodic_phase_rad)
        off += e.thermal_expansion_per_k * temp * (self.cfg.axis.nut_offset_m + q[self.tb])
        return off

    def _relax_contact(self, y: np.ndarray) -> None:
        """At rest the nut contact carries no force: move the table's bodies until the contact deflection
        (incidence . q + lead error + thermal growth) is zero, found by bracketed root finding on this model's
        own contact law (the kernel's simulator solves the same condition in closed form)."""
        if self.mech.contact is None or self.sb is None:
            return
        n = self.n
        moving = np.array([1.0 if b.name in ("table", "nut", "resonator") else 0.0 for b in self.mech.bodies])
        q0, temp = y[:n].copy(), y[2 * n + 2]

        def deflection(shift: float) -> float:
            q = q0 + shift * moving
            return float(self.a @ q) + self._kin(q, temp)

        if deflection(0.0) == 0.0:
            return
        span = 1e-3  # [m]: lead errors and thermal growth are micrometres
        shift = brentq(deflection, -span, span, xtol=1e-15, rtol=4 * np.finfo(float).eps)
        y[:n] = q0 + shift * moving

    def _contact_force(self, q, qd, temp):
        if self.mech.contact is None:
            return 0.0, 0
        delta = self.a @ q + self._kin(q, temp)
        dd = self.a @ qd
        half = self.cfg.backlash.gap_m / 2 if (self.cfg.backlash.enabled and self.cfg.backlash.gap_m > 0) else 0.0
        if half == 0.0:
            return self.kc * delta + self.cc * dd, 1
        if delta > half:
            return self.kc * (delta - half) + self.cc * dd, 1
        if delta < -half:
            return self.kc * (delta + half) + self.cc * dd, -1
        return 0.0, 0

    def _friction_slip(self, v, direction):
        f = self.cfg.friction
        d = direction if v == 0 else (1.0 if v > 0 else -1.0)
        fc = f.coulomb_n if d > 0 else (f.coulomb_negative_n if f.coulomb_negative_n >= 0 else f.coulomb_n)
        fv = f.viscous_n_s_per_m if d > 0 else (
            f.viscous_negative_n_s_per_m if f.viscous_negative_n_s_per_m >= 0 else f.viscous_n_s_per_m)
        return -d * (fc + f.stribeck_n * math.exp(-((abs(v) / f.stribeck_velocity_m_s) ** f.stribeck_exponent))) \
            - fv * v

    def _breakaway(self, fnet):
        f = self.cfg.friction
        fc = f.coulomb_n if fnet >= 0 else (f.coulomb_negative_n if f.coulomb_negative_n >= 0 else f.coulomb_n)
        return fc + f.stribeck_n

    def _rhs(self, t, y, ud, uq, fext, stuck, direction):
        n = self.n
        q, qd = y[:n], y[n:2 * n]
        idd, iqq, temp = y[2 * n], y[2 * n + 1], y[2 * n + 2]
        m = self.cfg.motor
        wm = self.mvec @ qd
        we = m.pole_pairs * wm
        did = (ud - m.rs_ohm * idd + we * m.lq_h * iqq) / m.ld_h
        diq = (uq - m.rs_ohm * iqq - we * (m.ld_h * idd + self.psi)) / m.lq_h
        torque = 1.5 * m.pole_pairs * (self.psi * iqq + (m.ld_h - m.lq_h) * idd * iqq)
        if m.cogging_amplitude_nm:
            angle = m.cogging_periods_per_rev * (self.mvec @ q) + m.cogging_phase_rad
            torque += m.cogging_amplitude_nm * math.sin(angle)
        kk, cc = self._matrices(q[self.tb])
        fcon, _ = self._contact_force(q, qd, temp)
        ffric = 0.0
        if self.cfg.friction.enabled and not stuck:
            ffric = self._friction_slip(qd[self.tb], direction)
        gen = self.g[:, 0] * torque + self.g[:, 2] * fext + self.g[:, 1] * ffric - self.a * fcon
        acc = -kk @ q - cc @ qd + self.minv @ gen
        if stuck:
            acc[self.tb] = 0.0
        dtemp = 0.0
        e = self.cfg.effects
        if e.thermal_expansion_per_k:
            p = 0.0 if stuck else abs(ffric * qd[self.tb])
            dtemp = (e.thermal_resistance_k_per_w * p - temp) / e.thermal_time_constant_s
        return np.concatenate([qd if not stuck else np.where(np.arange(n) == self.tb, 0.0, qd), acc, [did, diq, dtemp]])

    def _fnet_stuck(self, y, fext):
        n = self.n
        q, qd = y[:n], y[n:2 * n]
        kk, cc = self._matrices(q[self.tb])
        m_tab = 1.0 / self.minv[self.tb, self.tb]
        fcon, _ = self._contact_force(q, qd, y[2 * n + 2])
        gen = -self.a * fcon + self.g[:, 2] * fext
        # torque on the table row is zero for a rotary motor body
        return float(m_tab * (-(kk[self.tb] @ q) - cc[self.tb] @ qd) + gen[self.tb])

    # -------------------------------------------------------------------------------------------- run
    def run(self, t_cmd: np.ndarray, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> dict[str, np.ndarray]:
        cfg, c, m = self.cfg, self.cfg.control, self.cfg.motor
        n = self.n
        hc = c.current_cycle_s
        nspd = int(round(c.speed_cycle_s / hc))
        npos = int(round(c.position_cycle_s / hc))
        qenc = 2 * math.pi / cfg.sensors.motor_encoder_counts_per_rev if cfg.sensors.motor_encoder_counts_per_rev else 0
        qsc = cfg.sensors.linear_scale_resolution_m
        ndead = int(round(cfg.sensors.dead_time_s / hc))
        y = np.zeros(2 * n + 3)
        x0 = pos[0]
        for i, b in enumerate(self.mech.bodies):
            if b.name in ("table", "nut", "resonator"):
                y[i] = x0
            elif b.name in ("motor", "screw_end", "screw"):
                y[i] = x0 / self.r
        y[2 * n + 2] = cfg.effects.initial_temperature_rise_k
        self._relax_contact(y)
        # sensors.dead_time_scope = "feedback_sensor": the sensor read at t shows its value at t - D, linear between
        # the current-cycle instants around t - D (D = (n0 + frac) cycles); "position_loop": D rounded to cycles
        d_cycles = cfg.sensors.dead_time_s / hc
        n0 = int(math.floor(d_cycles + 1e-9))
        frac = max(d_cycles - n0, 0.0) if abs(d_cycles - round(d_cycles)) >= 1e-9 else 0.0
        hist = [(self.mvec @ y[:n], y[self.tb])] * (max(ndead, n0 + 1) + 1)

        def delayed(col: int) -> float:
            if not sensor_delayed:
                return hist[-1 - ndead][col]
            a, b = hist[-1 - n0][col], hist[-2 - n0][col]
            return a + frac * (b - a)
        stuck = cfg.friction.enabled
        direction = 1.0
        ud_app = uq_app = ud_next = uq_next = 0.0
        int_d = int_q = int_w = 0.0
        iq_ref = 0.0
        held = [0.0] * int(round(c.output_delay_s / c.speed_cycle_s))
        theta_prev = theta_prev2 = None
        w_filtered = 0.0
        two_sample = c.speed_estimator == "two_sample_difference"
        tau_w = c.speed_filter_time_constant_s
        sensor_delayed = cfg.sensors.dead_time_scope == "feedback_sensor"
        encoder_fb = c.position_feedback == "motor_encoder"
        setpoint_ff = c.velocity_ff_form == "setpoint_difference"
        v_prev = None
        jref = reflected_inertia_kg_m2(cfg)
        ilim = c.current_limit_a if c.current_limit_a > 0 else 3 * m.rated_current_a
        vmax = cfg.inverter.dc_link_v / math.sqrt(3)
        wlim = c.speed_limit_rpm * 2 * math.pi / 60 if c.speed_limit_rpm > 0 else 0.0
        out_pos = np.zeros(len(t_cmd))
        out_fb = np.zeros(len(t_cmd))
        out_iq = np.zeros(len(t_cmd))
        out_motor = np.zeros(len(t_cmd))
        t = 0.0
        for j in range(len(t_cmd)):
            d_th, d_x = delayed(0), delayed(1)
            fb = _q(d_th, qenc) * self.r if encoder_fb else _q(d_x, qsc)
            fe = pos[j] - fb
            v_ff, a_ff = vel[j], acc[j]
            if setpoint_ff and j > 0:  # a CSP drive: backward differences of the set-points
                v_ff = (pos[j] - pos[j - 1]) / c.position_cycle_s
                a_ff = (v_ff - v_prev) / c.position_cycle_s
            v_prev = v_ff
            wref = (c.kv_1_per_s * fe + c.velocity_ff_factor * v_ff) / self.r
            if wlim > 0:
                wref = max(-wlim, min(wlim, wref))
            tff = c.torque_ff_factor * jref * a_ff / self.r
            out_pos[j] = _q(d_x if sensor_delayed and not encoder_fb else y[self.tb], qsc)
            out_motor[j] = _q(d_th if sensor_delayed and encoder_fb else self.mvec @ y[:n], qenc)
            out_fb[j] = fb
            out_iq[j] = y[2 * n + 1]
            for k in range(npos):
                if k % nspd == 0:
                    # the speed loop's encoder: delayed when it is the delayed feedback sensor
                    th = _q(delayed(0) if sensor_delayed and encoder_fb else self.mvec @ y[:n], qenc)
                    if theta_prev is None:
                        theta_prev = theta_prev2 = th
                    if two_sample:
                        wraw = (th - theta_prev2) / (2 * hc * nspd)
                    else:
                        wraw = (th - theta_prev) / (hc * nspd)
                    theta_prev2, theta_prev = theta_prev, th
                    if tau_w > 0:
                        w_filtered += (1 - math.exp(-hc * nspd / tau_w)) * (wraw - w_filtered)
                        wmeas = w_filtered
                    else:
                        wmeas = wraw
                    ew = wref - wmeas
                    new_int = int_w + ew * hc * nspd / c.speed_ti_s if c.speed_ti_s > 0 else int_w
                    tref = c.speed_kp_nm_s_per_rad * (ew + new_int) + tff
                    int_w = new_int
                    lim = ilim * self.kt
                    if abs(tref) > lim:
                        tref = max(-lim, min(lim, tref))
                        if (tref > 0) == (ew > 0) and c.speed_ti_s > 0:
                            int_w -= ew * hc * nspd / c.speed_ti_s
                    held.append(tref / self.kt)  # applied output_delay_s after its samples
                    iq_ref = held.pop(0)
                ud_app, uq_app = ud_next, uq_next
                idd, iqq = y[2 * n], y[2 * n + 1]
                wm = self.mvec @ y[n:2 * n]
                we = m.pole_pairs * wm
                ffd = -we * m.lq_h * iqq if c.current_decoupling else 0.0
                ffq = we * (m.ld_h * idd + self.psi) if c.current_decoupling else 0.0
                nd = int_d + (-idd) * hc / c.current_ti_s if c.current_ti_s > 0 else int_d
                nq = int_q + (iq_ref - iqq) * hc / c.current_ti_s if c.current_ti_s > 0 else int_q
                ud = c.current_kp_v_per_a * (-idd + nd) + ffd
                uq = c.current_kp_v_per_a * (iq_ref - iqq + nq) + ffq
                mag = math.hypot(ud, uq)
                if mag > vmax:
                    ud, uq = ud * vmax / mag, uq * vmax / mag
                else:
                    int_d, int_q = nd, nq
                ud_next, uq_next = ud, uq
                t_end = t + hc
                while t < t_end - 1e-15:
                    y, t, stuck, direction = self._integrate(y, t, t_end, ud_app, uq_app, 0.0, stuck, direction)
                t = t_end
                hist.append((self.mvec @ y[:n], y[self.tb]))
                hist.pop(0)
        return {"t": np.asarray(t_cmd, float), "pos_meas": out_pos, "pos_fb": out_fb, "current_q": out_iq,
                "motor_pos": out_motor, "pos_cmd": np.asarray(pos, float)}

    def _integrate(self, y, t0, t1, ud, uq, fext, stuck, direction):
        n, tb = self.n, self.tb
        fric = self.cfg.friction.enabled
        events = []
        if fric and stuck:
            def ev_break(t, yy, *args):
                fnet = self._fnet_stuck(yy, fext)
                return abs(fnet) - self._breakaway(fnet)
            ev_break.terminal = True
            ev_break.direction = 1
            events.append(ev_break)
        elif fric:
            def ev_stop(t, yy, *args):
                return yy[n + tb] * direction
            ev_stop.terminal = True
            ev_stop.direction = -1
            events.append(ev_stop)
        # backlash contact changes are kinks of the contact force; the adaptive step size resolves them
        # the stuck state must start consistent
        if fric and stuck:
            fnet = self._fnet_stuck(y, fext)
            if abs(fnet) > self._breakaway(fnet):
                stuck = False
                direction = 1.0 if fnet > 0 else -1.0
        sol = solve_ivp(self._rhs, (t0, t1), y, method=self.method, rtol=self.rtol, atol=self.atol,
                        args=(ud, uq, fext, stuck, direction), events=events or None, max_step=t1 - t0)
        ynew = sol.y[:, -1].copy()
        tnew = sol.t[-1]
        if sol.status == 1:  # an event fired
            fired = [i for i, te in enumerate(sol.t_events) if len(te)]
            ev = events[fired[0]]
            name = ev.__name__
            if name == "ev_break":
                fnet = self._fnet_stuck(ynew, fext)
                stuck, direction = False, (1.0 if fnet > 0 else -1.0)
            elif name == "ev_stop":
                ynew[n + tb] = 0.0
                stuck = True
        return ynew, (t1 if sol.status == 0 else tnew), stuck, direction
