"""The axis simulator: control cascade + plant, as a step API (for the drive) and a batch API.

``AxisSimulator`` owns every array the compiled kernel touches, so stepping allocates nothing.
"""

from __future__ import annotations

import enum
import math
import types
from dataclasses import dataclass

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.config.axis import max_table_speed_m_s
from virtualaxis.control.loops import integral_gain_per_sample
from virtualaxis.control.options import fill_option_parameters
from virtualaxis.plant.discrete import DiscreteMechanics, discretise
from virtualaxis.plant.mechanics import feedforward_inertia, reflected_inertia_kg_m2
from virtualaxis.sim import layout as L
from virtualaxis.sim.brake import HoldingBrake
from virtualaxis.sim.kernel import run_cycles


class ControlMode(enum.IntEnum):
    POSITION = L.MODE_POSITION
    VELOCITY = L.MODE_VELOCITY
    TORQUE = L.MODE_TORQUE


#: the :class:`ControlMode` members as plain attributes (``CONTROL_MODE.POSITION is ControlMode.POSITION``): CPython
#: 3.11 looks an Enum member up through the class's descriptors, ~10x a plain attribute, and the drive cycle
#: compares modes several times per cycle
CONTROL_MODE = types.SimpleNamespace(**ControlMode.__members__)


@dataclass(frozen=True)
class AxisState:
    """A snapshot of the axis (SI units). ``torque_nm`` is N for a force actuator."""

    time_s: float
    position_m: float
    table_position_m: float
    motor_angle_rad: float
    motor_speed_rad_s: float
    velocity_m_s: float
    torque_nm: float
    current_q_a: float
    current_d_a: float
    voltage_q_v: float
    voltage_d_v: float
    following_error_m: float
    dc_link_v: float
    current_limited: bool
    voltage_saturated: bool
    friction_force_n: float
    stuck: bool
    screw_temperature_rise_k: float


class AxisReading:
    """The fields of :class:`AxisState`, mutable, refreshed in place by :meth:`AxisSimulator.observe` (the
    drive's per-cycle view of the plant: one object per simulator, no allocation per cycle)."""

    __slots__ = tuple(AxisState.__dataclass_fields__)

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0.0)
        self.current_limited = self.voltage_saturated = self.stuck = False


#: bodies that move with the table (positions in m); the rest are rotations
LINEAR_BODIES = ("table", "nut", "resonator")
#: cycles of sensor noise drawn at once by the step API [cycles]
NOISE_BLOCK = 256


def _ratio(outer: float, inner: float) -> int:
    return int(round(outer / inner))


#: hard end stops: least over-travel between the usable stroke (+-stroke/2) and the stop [m] (chosen: 10 mm,
#: the usual clearance between the STOP cams / limit switches and the mechanical end of a ball-screw axis)
END_STOP_MIN_OVERTRAVEL_M = 0.010
#: deceleration the over-travel is sized for [m/s^2] (chosen: half the 10 m/s^2 quick-stop default 0x6085, what
#: a heavy axis can still follow at its torque limit) ...
END_STOP_SIZING_DECEL_M_S2 = 5.0
#: ... with this margin on the braking distance (chosen: 1.5) ...
END_STOP_SIZING_MARGIN = 1.5
#: ... plus this reaction time at full speed [s] (chosen: 10 ms, limit-switch debounce + a few position cycles)
#: and the 2 mm between the limit switch and the stroke end
END_STOP_REACTION_S = 0.010
#: the buffer in front of the rigid stop: travel [m] (chosen: 10 mm, a polyurethane buffer of a machine axis) ...
END_STOP_BUFFER_TRAVEL_M = 0.010
#: ... natural frequency with the whole axis' mass as felt at the table [Hz] (chosen: 6 Hz, far below the axial
#: mode, so that rotor and table decelerate together and the screw spring does not throw the axis back) ...
END_STOP_BUFFER_HZ = 6.0
#: ... and damping ratio (chosen: 2, overdamped: a buffer absorbs the impact, it does not bounce)
END_STOP_BUFFER_DAMPING_RATIO = 2.0
#: rigid stop behind the buffer [N/m] (chosen: steel, 1e9 N/m = 1 mm at 1 MN) ...
END_STOP_STIFFNESS_N_PER_M = 1e9
#: ... limited so that the explicit contact force stays stable: omega h <= this at the table mass
END_STOP_MAX_OMEGA_H = 0.2
#: explicit damper stability: c h / m_table <= this
END_STOP_MAX_DAMPER_H = 0.5


def end_stop_mass_kg(cfg: AxisConfig) -> float:
    """Mass that runs into the end stop [kg]: table and nut plus every rotating inertia reflected through the
    lead (rotor, coupling, screw). For a heavy axis the rotor dominates (seed 000: 1329 kg, table + nut 152.5 kg)."""
    m = cfg.mechanics
    linear = m.table_mass_kg + m.nut_mass_kg + cfg.effects.resonance_mass_kg
    if cfg.actuator.kind == "force" or not m.lead_m > 0:
        return linear
    r = m.lead_m / (2 * math.pi)
    return reflected_inertia_kg_m2(cfg) / (r * r)


def end_stop_overtravel_m(cfg: AxisConfig) -> float:
    """Distance from the stroke end (+-stroke/2) to the end stop [m]: room to brake from the fastest speed the
    axis runs at (:func:`~virtualaxis.config.axis.max_table_speed_m_s`, which the drive's default 0x6080 allows)
    after the limit switch, at least :data:`END_STOP_MIN_OVERTRAVEL_M`. Seed 000 (3000/min x 16 mm = 0.8 m/s):
    106 mm; 0.5 m/s: 44.5 mm."""
    v = max_table_speed_m_s(cfg)
    need = 0.002 + END_STOP_SIZING_MARGIN * v * v / (2 * END_STOP_SIZING_DECEL_M_S2) + END_STOP_REACTION_S * v
    return max(END_STOP_MIN_OVERTRAVEL_M, need)


def end_stops(cfg: AxisConfig) -> tuple[float, float, float, float, float, float]:
    """The table's hard end stops: (lo [m], hi [m], buffer stiffness [N/m], buffer damping [N s/m], buffer
    travel [m], rigid-stop stiffness [N/m]). They sit at +-(stroke/2 + :func:`end_stop_overtravel_m`); a damped
    buffer (:data:`END_STOP_BUFFER_HZ` on :func:`end_stop_mass_kg`, damping ratio
    :data:`END_STOP_BUFFER_DAMPING_RATIO`) takes the first :data:`END_STOP_BUFFER_TRAVEL_M`, the rigid stop
    (:data:`END_STOP_STIFFNESS_N_PER_M`) the rest. Stiffness and damping are limited for stability of the
    explicit contact at the mechanical step h."""
    half = cfg.axis.stroke_m / 2 + end_stop_overtravel_m(cfg)
    h = cfg.control.current_cycle_s / cfg.simulation.mechanical_substeps
    m_table = cfg.mechanics.table_mass_kg + cfg.mechanics.nut_mass_kg
    m_all = max(end_stop_mass_kg(cfg), m_table)
    k_lim = (END_STOP_MAX_OMEGA_H / h) ** 2 * m_table
    w = 2 * math.pi * END_STOP_BUFFER_HZ
    k_buf = min(k_lim, w * w * m_all)
    c_buf = min(2.0 * END_STOP_BUFFER_DAMPING_RATIO * math.sqrt(k_buf * m_all), END_STOP_MAX_DAMPER_H * m_table / h)
    k_hard = max(min(END_STOP_STIFFNESS_N_PER_M, k_lim) - k_buf, 0.0)
    return -half, half, k_buf, c_buf, END_STOP_BUFFER_TRAVEL_M, k_hard


def build_parameters(cfg: AxisConfig, dm: DiscreteMechanics) -> np.ndarray:
    """Fill the kernel parameter vector from a validated config."""
    pr = np.zeros(L.N_PARAMS)
    c, mot, m = cfg.control, cfg.motor, cfg.mechanics
    force = cfg.actuator.kind == "force"
    r = m.lead_m / (2 * math.pi) if m.lead_m > 0 else 0.0
    hc = c.current_cycle_s
    pr[L.P_HC] = hc
    pr[L.P_NSPD] = _ratio(c.speed_cycle_s, hc)
    pr[L.P_NPOS] = _ratio(c.position_cycle_s, hc)
    pr[L.P_NSUB] = cfg.simulation.mechanical_substeps
    pr[L.P_HM] = hc / cfg.simulation.mechanical_substeps
    pr[L.P_PSI] = mot.psi_wb
    pr[L.P_KT] = mot.kt_nm_per_a
    pr[L.P_PP] = mot.pole_pairs
    pr[L.P_RS] = mot.rs_ohm
    pr[L.P_LD] = mot.ld_h
    pr[L.P_LQ] = mot.lq_h
    pr[L.P_EXP_D] = math.exp(-mot.rs_ohm * hc / mot.ld_h)
    pr[L.P_EXP_Q] = math.exp(-mot.rs_ohm * hc / mot.lq_h)
    pr[L.P_VDC] = cfg.inverter.dc_link_v
    pr[L.P_VMAX] = cfg.inverter.dc_link_v / math.sqrt(3.0)
    pr[L.P_SVPWM] = 1.0 if cfg.inverter.model == "svpwm" else 0.0
    pr[L.P_SVSUB] = cfg.inverter.svpwm_substeps
    pr[L.P_VMAX2] = pr[L.P_VMAX] ** 2
    pr[L.P_INV_RS] = 1.0 / mot.rs_ohm
    pr[L.P_GI_I] = integral_gain_per_sample(hc, c.current_ti_s)
    pr[L.P_GI_W] = integral_gain_per_sample(c.speed_cycle_s, c.speed_ti_s)
    pr[L.P_KPI] = c.current_kp_v_per_a
    pr[L.P_TII] = c.current_ti_s
    pr[L.P_DECOUP] = 1.0 if c.current_decoupling else 0.0
    pr[L.P_KPW] = c.velocity_kp_n_s_per_m if force else c.speed_kp_nm_s_per_rad
    pr[L.P_TIW] = c.speed_ti_s
    if force:
        pr[L.P_ILIM] = cfg.actuator.force_limit_n
    else:
        pr[L.P_ILIM] = c.current_limit_a if c.current_limit_a > 0 else 3.0 * mot.rated_current_a
    pr[L.P_G] = 1.0 if force else 1.0 / r
    if c.speed_limit_rpm > 0:
        w = c.speed_limit_rpm * 2 * math.pi / 60
        pr[L.P_WLIM] = w * r if force else w
    pr[L.P_KV] = c.kv_1_per_s
    pr[L.P_KFF] = c.velocity_ff_factor
    pr[L.P_KTFF] = c.torque_ff_factor
    pr[L.P_JREF] = feedforward_inertia(cfg)
    pr[L.P_R] = r
    pr[L.P_FB] = 1.0 if c.position_feedback == "linear_scale" else 0.0
    s = cfg.sensors
    pr[L.P_QENC] = 2 * math.pi / s.motor_encoder_counts_per_rev if s.motor_encoder_counts_per_rev > 0 else 0.0
    pr[L.P_QSCALE] = s.linear_scale_resolution_m
    pr[L.P_NDEAD] = int(round(s.dead_time_s / hc))
    if pr[L.P_NDEAD] >= L.RING_SIZE:
        from virtualaxis.config import ConfigError

        raise ConfigError(cfg.path, "sensors.dead_time_s", f"must be below {(L.RING_SIZE - 1) * hc:.4f} s")
    f = cfg.friction
    pr[L.P_FRIC] = 1.0 if f.enabled else 0.0
    pr[L.P_FC_POS] = f.coulomb_n
    pr[L.P_FC_NEG] = f.coulomb_negative_n if f.coulomb_negative_n >= 0 else f.coulomb_n
    pr[L.P_FS] = f.stribeck_n
    pr[L.P_VS] = f.stribeck_velocity_m_s
    pr[L.P_DELTA] = f.stribeck_exponent
    pr[L.P_FV] = f.viscous_n_s_per_m
    pr[L.P_BL] = 1.0 if (cfg.backlash.enabled and cfg.backlash.gap_m > 0) else 0.0
    pr[L.P_BL_HALF] = cfg.backlash.gap_m / 2
    pr[L.P_COG_A] = 0.0 if force else mot.cogging_amplitude_nm
    pr[L.P_COG_N] = mot.cogging_periods_per_rev
    pr[L.P_COG_PH] = mot.cogging_phase_rad
    e = cfg.effects
    pr[L.P_LEAD_PPM] = e.lead_error_ppm
    pr[L.P_LEAD_PER_A] = e.lead_error_periodic_m
    pr[L.P_LEAD_PER_PH] = e.lead_error_periodic_phase_rad
    pr[L.P_TH_ALPHA] = e.thermal_expansion_per_k
    pr[L.P_TH_R] = e.thermal_resistance_k_per_w
    pr[L.P_TH_TAU] = e.thermal_time_constant_s
    pr[L.P_NUT_OFF] = cfg.axis.nut_offset_m
    pr[L.P_GRID_LO] = dm.grid_m[0]
    pr[L.P_GRID_STEP] = (dm.grid_m[-1] - dm.grid_m[0]) / max(len(dm.grid_m) - 1, 1)
    pr[L.P_NGRID] = len(dm.grid_m)
    pr[L.P_FORCE_ACT] = 1.0 if force else 0.0
    pr[L.P_FORCE_LAG] = cfg.actuator.force_lag_s
    pr[L.P_NOISE_POS] = s.position_noise_m
    pr[L.P_NOISE_I] = s.current_noise_a
    pr[L.P_TABLE] = dm.table_body
    pr[L.P_SCREW] = dm.screw_body
    pr[L.P_NDOF] = dm.n
    pr[L.P_KC] = dm.contact_stiffness
    pr[L.P_HAS_CONTACT] = 1.0 if np.any(dm.contact_vector != 0) else 0.0
    lo, hi, k, c, travel, k_hard = end_stops(cfg)
    pr[L.P_STOP_LO], pr[L.P_STOP_HI], pr[L.P_STOP_K], pr[L.P_STOP_C] = lo, hi, k, c
    pr[L.P_STOP_TRAVEL], pr[L.P_STOP_KH] = travel, k_hard
    nz = np.flatnonzero(dm.motor_angle_vector)
    pr[L.P_MOTOR_IDX] = nz[0] if (len(nz) == 1 and dm.motor_angle_vector[nz[0]] == 1.0) else -1
    fill_option_parameters(pr, cfg)  # drive / axis options (control/options.py)
    return pr


def _finite(what: str, *values: float) -> None:
    """Refuse NaN / inf at the plant's boundary (they would poison the state for good)."""
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f"{what} must be finite (got {v!r})")


class AxisSimulator:
    """Control cascade + plant, stepped one position-loop cycle at a time (see docs/architecture.md)."""

    def __init__(self, cfg: AxisConfig, seed: int | None = None, initial_position_m: float = 0.0,
                 *, discrete: DiscreteMechanics | None = None):
        self.cfg = cfg
        self.cycle_s = cfg.control.position_cycle_s
        hm = cfg.control.current_cycle_s / cfg.simulation.mechanical_substeps
        self.dm = discrete if discrete is not None else discretise(cfg, hm)
        self.pr = build_parameters(cfg, self.dm)
        n = self.dm.n
        s = 2 * n
        self.st = np.zeros(L.Z0 + s)
        self.ring = np.zeros((L.RING_SIZE, 2))
        self.wat = np.zeros((4, s, s))  # blended Ad per mode, transposed: wat[m, c, r] = Ad[m, r, c]
        self.wbt = np.zeros((4, 4, s))  # blended Bd per mode, transposed
        self.wk = np.zeros((2, n))
        self.wc = np.zeros((2, n))
        self.ztmp = np.zeros(s)
        # the mode tables transposed per grid point and mode (column-wise step in the kernel)
        self._adt = np.ascontiguousarray(np.swapaxes(self.dm.ad, 2, 3))
        self._bdt = np.ascontiguousarray(np.swapaxes(self.dm.bd, 2, 3))
        self._rng = np.random.default_rng(cfg.simulation.seed if seed is None else seed)
        # one-cycle buffers of the step API (preallocated: a step allocates nothing but the kernel call)
        self._one = {k: np.zeros(1) for k in ("pos", "vel", "acc", "aux", "fext")}
        self._pos1, self._vel1, self._acc1 = self._one["pos"], self._one["vel"], self._one["acc"]
        self._aux1, self._fext1 = self._one["aux"], self._one["fext"]
        self._force_offset = -float(cfg.effects.force_offset_n)  # a load against +x: external force -offset
        #: the holding brake (None: the axis has none); its holding force goes to the kernel every cycle
        self.brake = HoldingBrake.of(cfg)
        if self.brake is not None:
            self.pr[L.P_BRAKE_N] = self.brake.holding_force_n
        self._one["fext"][0] = self._force_offset
        self._noise1 = np.zeros((1, 2))
        # sensor noise of the step API drawn NOISE_BLOCK cycles at a time (the same stream as one draw of 2
        # per cycle: numpy's Generator fills an array element by element); row views made once
        self._noisy = bool(self.pr[L.P_NOISE_POS] or self.pr[L.P_NOISE_I])
        self._noise_block = np.zeros((NOISE_BLOCK, 2))
        self._noise_rows = [self._noise_block[i:i + 1] for i in range(NOISE_BLOCK)]
        self._noise_next = NOISE_BLOCK  # next unused row of the block (NOISE_BLOCK: none drawn)
        self._out1 = np.zeros((1, L.N_OUT))
        self._last = self._out1[0]  # the outputs at the start of the last simulated cycle (a view, no copy)
        self._reading = AxisReading()
        self._velocity_setpoint = 0.0
        self._torque_setpoint = 0.0
        self._force_actuator = bool(self.pr[L.P_FORCE_ACT] != 0)
        self._motor_index = int(self.pr[L.P_MOTOR_IDX])
        self._motor_vector = [float(x) for x in self.dm.motor_angle_vector]
        self._dc_link_v = float(cfg.inverter.dc_link_v)
        self._step_kernel = run_cycles
        self.reset(initial_position_m)
        self._step_kernel = self._compiled_step_kernel()

    # ----------------------------------------------------------------------------------------- state
    def reset(self, position_m: float = 0.0, *, keep_time: bool = False) -> None:
        """Put the axis at rest at ``position_m`` (table), disabled, position mode (``keep_time``: the
        simulated time runs on, e.g. for a drive's power-on reset)."""
        t = float(self.st[L.S_T]) if keep_time and math.isfinite(float(self.st[L.S_T])) else 0.0
        self.st[:] = 0.0
        self.st[L.S_T] = t
        r = self.pr[L.P_R]
        names = self.dm.body_names
        for i, name in enumerate(names):
            if name in LINEAR_BODIES:
                self.st[L.Z0 + i] = position_m
            elif name in ("motor", "screw_end", "screw") and r > 0:
                self.st[L.Z0 + i] = position_m / r
        self.st[L.S_DIR] = 1.0
        self.st[L.S_POS_FB] = position_m
        self.st[L.S_CMD_POS] = position_m
        self.st[L.S_STUCK] = 1.0 if self.cfg.friction.enabled or self.pr[L.P_BRAKE_N] else 0.0
        self.st[L.S_TEMP] = self.cfg.effects.initial_temperature_rise_k
        # at rest means the nut contact is relaxed: with a lead error or a warm screw the table sits where the
        # screw's kinematics put it for this screw angle, not at the nominal position_m (else the contact
        # spring starts preloaded and the axis jumps at t = 0: 0.48 um at 60 ppm 5 mm from the nut offset)
        table_m = position_m + self._kinematic_shift_m()
        if table_m != position_m:
            for i, name in enumerate(names):
                if name in LINEAR_BODIES:
                    self.st[L.Z0 + i] = table_m
            if self.pr[L.P_FB] != 0.0:  # linear-scale feedback reads the table
                self.st[L.S_POS_FB] = table_m
        self.ring[:, 0] = position_m / r if r > 0 else 0.0
        self.ring[:, 1] = table_m
        self._last[:] = 0.0
        self._last[L.O_POS_FB] = self.st[L.S_POS_FB]
        self._last[L.O_TABLE_TRUE] = table_m
        self._last[L.O_POS_MEAS] = table_m
        self._last[L.O_POS_CMD] = position_m
        self._one["pos"][0] = position_m

    def _kinematic_shift_m(self) -> float:
        """How far the table (with nut and resonator) must move from the nominal position so that the nut
        contact is relaxed at the present screw angle [m]: the kernel's contact deflection
        ``kin + contact_vector . z`` set to zero, where ``kin`` is the lead error (cumulative, periodic) and the
        thermal growth of the screw (which itself depends on the table position: solved exactly, it is linear)."""
        pr, dm = self.pr, self.dm
        sb = int(pr[L.P_SCREW])
        if pr[L.P_HAS_CONTACT] == 0.0 or sb < 0:
            return 0.0
        n, tb = dm.n, dm.table_body
        z = self.st[L.Z0:L.Z0 + n]
        theta = float(z[sb])
        growth = float(pr[L.P_TH_ALPHA] * self.st[L.S_TEMP])  # thermal strain of the screw [-]
        kin = (pr[L.P_LEAD_PPM] * 1e-6 * pr[L.P_R] * theta
               + pr[L.P_LEAD_PER_A] * math.sin(theta + pr[L.P_LEAD_PER_PH])
               + growth * (pr[L.P_NUT_OFF] + z[tb]))
        moving = np.array([1.0 if name in LINEAR_BODIES else 0.0 for name in dm.body_names])
        delta = float(kin + dm.contact_vector @ z)
        slope = float(dm.contact_vector @ moving) + growth
        if delta == 0.0 or slope == 0.0:
            return 0.0
        return -delta / slope

    def enable(self, on: bool = True) -> None:
        self.st[L.S_ENABLED] = 1.0 if on else 0.0
        if not on:
            self.st[L.S_INT_W] = 0.0

    @property
    def enabled(self) -> bool:
        return bool(self.st[L.S_ENABLED])

    def set_mode(self, mode: ControlMode) -> None:
        mode = ControlMode(mode)
        # position <-> velocity control share the speed controller: its integrator carries over (bumpless);
        # it restarts only when torque control is entered or left
        if mode != self.mode and ControlMode.TORQUE in (mode, self.mode):
            self.st[L.S_INT_W] = 0.0
        self.st[L.S_MODE] = int(mode)

    @property
    def mode(self) -> ControlMode:
        return ControlMode(int(self.st[L.S_MODE]))

    def set_position_setpoint(self, pos_m: float, vel_ff_m_s: float = 0.0, acc_ff_m_s2: float = 0.0) -> None:
        _finite("position set-point", pos_m, vel_ff_m_s, acc_ff_m_s2)
        self._one["pos"][0] = pos_m
        self._one["vel"][0] = vel_ff_m_s
        self._one["acc"][0] = acc_ff_m_s2

    def set_velocity_setpoint(self, vel_m_s: float) -> None:
        _finite("velocity set-point", vel_m_s)
        self._velocity_setpoint = vel_m_s

    def set_torque_setpoint(self, torque: float) -> None:
        _finite("torque set-point", torque)
        self._torque_setpoint = torque

    def set_external_force(self, force_n: float) -> None:
        _finite("external force", force_n)
        self._one["fext"][0] = force_n + self._force_offset  # effects.force_offset_n: constant external force

    def command_brake(self, released: bool) -> None:
        """Energise (``released``) or de-energise the holding brake's coil now; it follows after its opening /
        closing time (:class:`~virtualaxis.sim.brake.HoldingBrake`). Without a brake: nothing."""
        if self.brake is not None:
            self.brake.command(released, float(self.st[L.S_T]))

    def brake_released(self) -> bool:
        """Whether the holding brake is released now (True without a brake: nothing holds the axis)."""
        return self.brake is None or self.brake.is_released(float(self.st[L.S_T]))

    def advance(self, n_cycles: int = 1) -> None:
        """Run ``n_cycles`` position-loop cycles with the present set-points (hot path: no allocation, no enum;
        one compiled kernel call per cycle)."""
        mode = self.st[L.S_MODE]
        self._aux1[0] = self._torque_setpoint if mode == L.MODE_TORQUE else self._velocity_setpoint
        if mode != L.MODE_POSITION:
            self._pos1[0] = self._last[L.O_POS_FB]
        d = self.dm
        kernel = self._step_kernel
        brake = self.brake
        for _ in range(n_cycles):
            if brake is not None:  # (its force at the start of the cycle, held through the cycle)
                self.pr[L.P_BRAKE_N] = brake.force_n(self.st[L.S_T])
            if self._noisy:
                i = self._noise_next
                if i == NOISE_BLOCK:
                    self._rng.standard_normal(out=self._noise_block)
                    i = 0
                self._noise_next = i + 1
                noise = self._noise_rows[i]
            else:
                noise = self._noise1
            kernel(self.st, self.pr, self._adt, self._bdt, d.table_k_row, d.table_c_row, d.table_g_row,
                   d.contact_vector, d.motor_angle_vector, self.ring, self.wat, self.wbt, self.wk, self.wc, self.ztmp,
                   self._pos1, self._vel1, self._acc1, self._aux1, self._fext1, noise, self._out1)

    def preview(self) -> np.ndarray:
        """The output row (``layout.O_*``) the next :meth:`advance` records at its first sampling instant: the
        signals now, as the drive samples them, with the present set-points. Nothing advances: the kernel runs
        that cycle on copies of the state (the sensor noise is the row the next cycle uses)."""
        mode = self.st[L.S_MODE]
        self._aux1[0] = self._torque_setpoint if mode == L.MODE_TORQUE else self._velocity_setpoint
        if mode != L.MODE_POSITION:
            self._pos1[0] = self._last[L.O_POS_FB]
        if self._noisy:
            if self._noise_next == NOISE_BLOCK:
                self._rng.standard_normal(out=self._noise_block)
                self._noise_next = 0
            noise = self._noise_rows[self._noise_next]
        else:
            noise = self._noise1
        st = self.st.copy()
        ring = self.ring.copy()
        out = np.zeros((1, L.N_OUT))
        d = self.dm
        self._step_kernel(st, self.pr, self._adt, self._bdt, d.table_k_row, d.table_c_row, d.table_g_row,
                          d.contact_vector, d.motor_angle_vector, ring, self.wat, self.wbt, self.wk, self.wc,
                          self.ztmp, self._pos1, self._vel1, self._acc1, self._aux1, self._fext1, noise, out)
        return out[0]

    def _compiled_step_kernel(self):
        """The kernel's compiled entry point for the step API's own arrays (skips numba's per-call type
        dispatch, ~1 us); the dispatcher itself if numba does not offer it."""
        d = self.dm
        args = (self.st, self.pr, self._adt, self._bdt, d.table_k_row, d.table_c_row, d.table_g_row,
                d.contact_vector, d.motor_angle_vector, self.ring, self.wat, self.wbt, self.wk, self.wc, self.ztmp,
                self._pos1, self._vel1, self._acc1, self._aux1, self._fext1, self._noise_rows[0], self._out1)
        try:
            sig = tuple(run_cycles.typeof_pyval(a) for a in args)
            if sig not in run_cycles.overloads:
                run_cycles.compile(sig)
            return run_cycles.overloads[sig].entry_point
        except Exception:  # noqa: BLE001 - a numba without these internals: the (slower) dispatcher
            return run_cycles

    def _run(self, pos, vel, acc, aux, fext, noise, out) -> None:
        d = self.dm
        run_cycles(self.st, self.pr, self._adt, self._bdt, d.table_k_row, d.table_c_row, d.table_g_row,
                   d.contact_vector, d.motor_angle_vector, self.ring, self.wat, self.wbt, self.wk, self.wc, self.ztmp,
                   pos, vel, acc, aux, fext, noise, out)

    @property
    def time_s(self) -> float:
        return float(self.st[L.S_T])

    def observe(self) -> AxisReading:
        """The axis now, written into ONE reading object owned by the simulator (the same object every call,
        refreshed in place: no allocation per cycle; read its fields before the next ``observe``). For a
        snapshot that stays as it is use :attr:`state`."""
        st = self.st.tolist()  # one conversion; plain floats from here on (the drive reads this every cycle)
        r = self._reading
        n, tb = self.dm.n, self.dm.table_body
        z0 = L.Z0
        if self._motor_index >= 0:
            r.motor_angle_rad = st[z0 + self._motor_index]
            r.motor_speed_rad_s = st[z0 + n + self._motor_index]
        else:
            mv = self._motor_vector
            r.motor_angle_rad = sum(mv[i] * st[z0 + i] for i in range(n))
            r.motor_speed_rad_s = sum(mv[i] * st[z0 + n + i] for i in range(n))
        t = st[L.S_T]
        r.time_s = t
        r.position_m = st[L.S_POS_FB] if t > 0 else float(self._last[L.O_POS_FB])
        r.table_position_m = st[z0 + tb]
        r.velocity_m_s = st[z0 + n + tb]
        r.torque_nm = st[L.S_TORQUE]
        if self._force_actuator:
            r.current_q_a = r.current_d_a = 0.0
        else:
            r.current_q_a = st[L.S_IQ]
            r.current_d_a = st[L.S_ID]
        r.voltage_q_v = st[L.S_UQ_APP]
        r.voltage_d_v = st[L.S_UD_APP]
        r.following_error_m = st[L.S_FE]
        r.dc_link_v = self._dc_link_v
        r.current_limited = st[L.S_ILIM] != 0.0
        r.voltage_saturated = st[L.S_VSAT] != 0.0
        r.friction_force_n = st[L.S_F_FRIC]
        r.stuck = st[L.S_STUCK] != 0.0
        r.screw_temperature_rise_k = st[L.S_TEMP]
        return r

    @property
    def current_cycles_per_cycle(self) -> int:
        """Current-loop cycles per position-loop cycle."""
        return int(self.pr[L.P_NPOS])

    def state_within_cycle(self, current_cycles: int) -> AxisState:
        """The axis state ``current_cycles`` current-loop cycles into the next position-loop cycle (0 <= it <
        :attr:`current_cycles_per_cycle`), with the present set-points. Nothing advances: the kernel runs that
        cycle's position-loop sample and its first ``current_cycles`` current-loop cycles on copies of the state,
        exactly as :meth:`advance` runs them (the set-points and the external force are sampled at the start of
        a position-loop cycle)."""
        if not 0 <= current_cycles < self.current_cycles_per_cycle:
            raise ValueError(f"current_cycles must be in [0, {self.current_cycles_per_cycle}) "
                             f"(got {current_cycles!r})")
        if current_cycles == 0:
            return self.state
        mode = self.st[L.S_MODE]
        self._aux1[0] = self._torque_setpoint if mode == L.MODE_TORQUE else self._velocity_setpoint
        if mode != L.MODE_POSITION:
            self._pos1[0] = self._last[L.O_POS_FB]
        st = self.st.copy()
        pr = self.pr.copy()
        pr[L.P_NPOS] = current_cycles  # the cycle ends after these current cycles (only its power and ripple
        # averages, not returned here, divide by the count)
        out = np.zeros((1, L.N_OUT))
        d = self.dm
        self._step_kernel(st, pr, self._adt, self._bdt, d.table_k_row, d.table_c_row, d.table_g_row,
                          d.contact_vector, d.motor_angle_vector, self.ring.copy(), self.wat, self.wbt, self.wk,
                          self.wc, self.ztmp, self._pos1, self._vel1, self._acc1, self._aux1, self._fext1,
                          self._noise1, out)
        return self._state_of(st)

    @property
    def state(self) -> AxisState:
        return self._state_of(self.st)

    def _state_of(self, state_vector: np.ndarray) -> AxisState:
        st = state_vector.tolist()  # one conversion; plain floats from here on
        n, tb = self.dm.n, self.dm.table_body
        force = self._force_actuator
        z0 = L.Z0
        if self._motor_index >= 0:
            angle = st[z0 + self._motor_index]
            speed = st[z0 + n + self._motor_index]
        else:
            mv = self._motor_vector
            angle = sum(mv[i] * st[z0 + i] for i in range(n))
            speed = sum(mv[i] * st[z0 + n + i] for i in range(n))
        return AxisState(
            time_s=st[L.S_T],
            position_m=st[L.S_POS_FB] if st[L.S_T] > 0 else float(self._last[L.O_POS_FB]),
            table_position_m=st[z0 + tb],
            motor_angle_rad=angle,
            motor_speed_rad_s=speed,
            velocity_m_s=st[z0 + n + tb],
            torque_nm=st[L.S_TORQUE],
            current_q_a=0.0 if force else st[L.S_IQ],
            current_d_a=0.0 if force else st[L.S_ID],
            voltage_q_v=st[L.S_UQ_APP],
            voltage_d_v=st[L.S_UD_APP],
            following_error_m=st[L.S_FE],
            dc_link_v=self._dc_link_v,
            current_limited=bool(st[L.S_ILIM]),
            voltage_saturated=bool(st[L.S_VSAT]),
            friction_force_n=st[L.S_F_FRIC],
            stuck=bool(st[L.S_STUCK]),
            screw_temperature_rise_k=st[L.S_TEMP],
        )

    # ----------------------------------------------------------------------------------------- gains
    def set_loop_gains(
        self,
        *,
        kv_per_s: float | None = None,
        velocity_ff_factor: float | None = None,
        torque_ff_factor: float | None = None,
        speed_kp: float | None = None,
        speed_ti_s: float | None = None,
        current_limit: float | None = None,
        speed_limit_m_s: float | None = None,
    ) -> None:
        """Change control-loop parameters while running (the drive's 0x2000-0x2004, 0x6072/0x6073, 0x6080).

        ``speed_kp`` is N m s/rad (pmsm) or N s/m (force actuator); ``speed_ti_s`` = 0 makes the speed loop P
        only; ``current_limit`` is A (pmsm) or N (force actuator); ``speed_limit_m_s`` limits the speed
        set-point, expressed as table speed (0 = no limit; ignored on a direct drive without a lead).
        Derived kernel constants are updated too.
        """
        pr = self.pr
        if kv_per_s is not None:
            pr[L.P_KV] = kv_per_s
        if velocity_ff_factor is not None:
            pr[L.P_KFF] = velocity_ff_factor
        if torque_ff_factor is not None:
            pr[L.P_KTFF] = torque_ff_factor
        if speed_kp is not None:
            pr[L.P_KPW] = speed_kp
        if speed_ti_s is not None:
            pr[L.P_TIW] = speed_ti_s
            pr[L.P_GI_W] = integral_gain_per_sample(self.cfg.control.speed_cycle_s, speed_ti_s)
        if current_limit is not None:
            pr[L.P_ILIM] = current_limit
        if speed_limit_m_s is not None:
            if self._force_actuator:
                pr[L.P_WLIM] = max(0.0, speed_limit_m_s)
            elif pr[L.P_R] > 0:
                pr[L.P_WLIM] = max(0.0, speed_limit_m_s) / pr[L.P_R]

    @property
    def torque_constant_nm_per_a(self) -> float:
        return float(self.pr[L.P_KT])

    # ----------------------------------------------------------------------------------------- batch
    def run_arrays(self, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, fext: np.ndarray,
                   aux: np.ndarray | None = None, chunk: int = 20000, callback=None) -> np.ndarray:
        """Run a whole command (one entry per position cycle) and return the output rows ``(n, N_OUT)``.

        ``callback(rows_done)`` is called after each chunk (progress bars, streaming writers).
        """
        n = len(pos)
        out = np.zeros((n, L.N_OUT))
        if self._force_offset:  # effects.force_offset_n: constant load, on top of fext
            fext = np.asarray(fext, dtype=float) + self._force_offset
        if aux is None:
            aux = np.zeros(n)
        noise = np.zeros((n, 2))
        if self.pr[L.P_NOISE_POS] or self.pr[L.P_NOISE_I]:
            # the step API's drawn-ahead noise first, so the stream is the same however the calls are mixed
            k = min(n, NOISE_BLOCK - self._noise_next)
            if k > 0:
                noise[:k] = self._noise_block[self._noise_next:self._noise_next + k]
                self._noise_next += k
            if n > k:
                noise[k:] = self._rng.standard_normal((n - k, 2))
        for a in range(0, n, chunk):
            b = min(n, a + chunk)
            self._run(pos[a:b], vel[a:b], acc[a:b], aux[a:b], fext[a:b], noise[a:b], out[a:b])
            if callback:
                callback(b)
        if n:
            self._last[:] = out[-1]
        return out
