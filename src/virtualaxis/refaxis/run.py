"""One recorded run of a reference axis: command in, trace columns out (what a drive trace would hold).

Recording conventions (row k = position-loop instant t_k = k T, T = 1 ms):

* ``pos_cmd``: the command the position loop used at t_k.
* ``pos_meas``: linear scale at t_k (quantised, white noise). On ``rigid_pp`` and ``full_closed`` the scale is
  also the position loop's feedback, so the channel is exactly what the controller read (including a feedback
  dead time, if any); on ``two_mass`` it is a measuring scale outside the loop.
* ``pos_fb`` (two_mass only): motor encoder at the table (r x encoder angle) as the position loop read it at t_k.
* ``motor_pos`` (two_mass, full_closed): the encoder angle [rad], 0 with the table at 0.
* ``current_q`` (two_mass, full_closed): torque-producing current sampled at t_k (torque / kt, quantised, noisy);
  ``force_drive`` = current_q x kt x 2 pi / lead (the drive's force at the nut).
* ``force_ext``: the known external force on the table (pulses of the rigid axis' validation run), exact.
* ``force_drive`` (rigid_pp): the controller's force command; by default row k holds the command applied
  during [t_k-1, t_k) (computed at t_k-1); with ``channel_shift = 1`` row k holds the command computed at t_k
  (applied during [t_k, t_k+1)): the channel then leads our convention by one sample.
"""

from __future__ import annotations

import zlib

import numpy as np

from virtualaxis.refaxis import axes as A
from virtualaxis.refaxis import kernel as K

PREROLL_S = 0.5


def _quantise(x: np.ndarray, q: float) -> np.ndarray:
    return np.round(x / q) * q if q > 0 else x


def noise_seed(*parts: object) -> int:
    """A seed stable across processes (``hash`` of a str is salted per process)."""
    return zlib.crc32("|".join(str(p) for p in parts).encode())


def simulate(structure: str, phys: dict, x_cmd: np.ndarray, seed: int, *, record_from: int = 0,
             channel_shift: int = 0, f_ext: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Simulate ``x_cmd`` (1 kHz, metres) on the axis ``phys`` and return the trace columns (SI units).

    A standstill of ``PREROLL_S`` at the first command value runs before the command (not recorded; the
    axis settles, enabled). ``record_from``: first command sample recorded (a start already moving).
    ``f_ext``: known external force on the table along +x per command sample [N], recorded as ``force_ext``."""
    T = phys["position_cycle_s"]
    n_pre = int(round(PREROLL_S / T))
    cmd = np.concatenate([np.full(n_pre, x_cmd[0]), x_cmd])
    n = cmd.shape[0]
    fext = np.zeros(n) if f_ext is None else np.concatenate([np.zeros(n_pre), f_ext])
    p = A.kernel_vector(structure, phys)
    rng = np.random.default_rng(seed)
    n_speed = int(p[K.P_N_SPEED])
    enc_noise = rng.standard_normal(n * n_speed)
    fb_noise = rng.standard_normal(n)
    s0 = np.zeros(6)
    integ0 = 0.0
    u0 = 0.0
    if structure in A.SCREW_STRUCTURES:
        r = p[K.P_R_M_PER_RAD]
        th0 = cmd[0] / r
        pos, g = K.screw_position(p, th0, p[K.P_DTEMP0_K])
        f_static = phys["force_offset_n"]
        k = K.axial_stiffness(p, cmd[0])
        side = np.sign(f_static) if f_static != 0 else 0.0
        s0[0] = th0
        s0[2] = pos - f_static / k - side * 0.5 * p[K.P_GAP_M]
        integ0 = u0 = f_static * g
    else:
        s0[2] = cmd[0]
    s0[4] = s0[2]
    u_add = np.zeros(n)
    raw, *_ = K.run_axis(p, cmd, u_add, fext, enc_noise, fb_noise, s0, 0.0, integ0, u0)
    first = n_pre + record_from
    u_prev = raw[first - 1:-1, K.C_U_CMD].copy()  # command computed at t_k-1 (the pre-roll precedes row 0)
    raw = raw[first:]
    x_rec = cmd[n_pre + record_from:]
    m = raw.shape[0]
    t = np.arange(m) * T
    cols: dict[str, np.ndarray] = {"t": t, "pos_cmd": x_rec}
    if f_ext is not None:
        cols["force_ext"] = np.asarray(f_ext, dtype=float)[record_from:]
    if structure in A.SCREW_STRUCTURES:
        if phys["full_closed"]:
            cols["pos_meas"] = raw[:, K.C_FB]  # the scale as the position loop read it
        else:
            cols["pos_meas"] = _quantise(raw[:, K.C_X_TABLE] + phys["scale_noise_m"] * rng.standard_normal(m),
                                         phys["scale_quantum_m"])
            cols["pos_fb"] = raw[:, K.C_FB]
        kt = phys["torque_constant_nm_per_a"]
        iq = _quantise(raw[:, K.C_U_ACT] / kt + phys["current_noise_a"] * rng.standard_normal(m),
                       phys["current_quantum_a"])
        cols["force_drive"] = iq * kt / A.radius_m_per_rad(phys)
        cols["motor_pos"] = raw[:, K.C_THETA_MEAS]
        cols["current_q"] = iq
    else:
        cols["pos_meas"] = raw[:, K.C_FB]
        force = raw[:, K.C_U_CMD] if channel_shift == 1 else u_prev
        cols["force_drive"] = _quantise(force, phys["force_quantum_n"])
    return cols
