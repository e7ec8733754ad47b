"""Per-axis bounds of the loop-gain objects 0x2003 (speed controller P gain), 0x2000 (position loop Kv) and
0x2004 (speed controller integral time Tn).

A cascade loop is tuned slower than the loop it commands: the speed loop's crossover Kp / J below the current
loop's bandwidth and the speed cycle's Nyquist frequency, the position loop's Kv below the speed loop's. A
speed-loop crossover beyond what the current loop follows makes the speed controller switch the current
set-point between its limits every speed cycle, and the current loop then overshoots the current limit. The
drive refuses a gain beyond these bounds (SDO abort 0x06090031; a Tn below its bound 0x06090032), computed
from the axis config at drive start (docs/drive.md, "Loop-gain bounds"):

- current-loop bandwidth w_i [rad/s]: K_p,i / L_q of a PMSM (the PI zero cancels the winding's R / L pole; the
  closed current loop is then a first-order lag 1 / (1 + s L_q / K_p,i)); 1 / actuator.force_lag_s of a force
  actuator (pi / current cycle without a lag);
- speed-loop crossover w_n,max = min(w_i, pi / T_speed) / SPEED_LOOP_MARGIN, speed Kp max = w_n,max x J, J the
  reflected inertia at the motor [kg m^2] (a force actuator: the moving mass [kg]);
- Kv max = min(w_n,max, pi / T_position) / POSITION_LOOP_MARGIN [1/s], in 0x2000's unit 1000/min x 60 / 1000;
- speed integral time Tn (0x2004) min = SPEED_TN_FACTOR / w_n,max (0 stays legal: a P-only speed loop); the
  integrator alone then oscillates at most at sqrt(Kp / (Tn J)) <= w_n,max / 2 whatever the accepted Kp, and
  a PI zero 1 / Tn at most a quarter of the fastest crossover is the symmetric optimum's Tn = 4 / w_n.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from virtualaxis.config import AxisConfig
from virtualaxis.plant.mechanics import feedforward_inertia

#: the speed loop's crossover at most 1/2 of the current loop's bandwidth (and of the speed cycle's Nyquist
#: frequency): the cascade rule of thumb's widest spacing (chosen; the seed axis is commissioned at 1/6)
SPEED_LOOP_MARGIN = 2.0
#: Kv at most 1/4 of the fastest speed loop (and of the position cycle's Nyquist frequency): the usual
#: spacing of a position loop over its speed loop (chosen; the seed axis: 92 1/s over 800 rad/s, 1/8.7)
POSITION_LOOP_MARGIN = 4.0
#: Tn at least 4 / w_n,max (the symmetric optimum's integral time at the fastest accepted crossover)
SPEED_TN_FACTOR = 4.0


@dataclass(frozen=True)
class LoopGainBounds:
    """The loop gains the drive accepts on one axis: speed Kp and Kv up to their maximum, Tn 0 or from its
    minimum."""

    current_bandwidth_rad_s: float
    speed_crossover_max_rad_s: float
    inertia: float  # reflected inertia at the motor [kg m^2], or the moving mass [kg] of a force actuator
    speed_kp_max: float  # 0x2003's unit: N m s/rad (pmsm) or N s/m (force actuator)
    kv_max_per_s: float
    speed_tn_min_s: float  # the smallest integral time > 0 accepted (0 = P only is accepted too)

    @property
    def kv_max_1000_per_min(self) -> float:
        """Kv max in 0x2000's unit [1000/min]."""
        return self.kv_max_per_s * 60.0 / 1000.0


def loop_gain_bounds(cfg: AxisConfig) -> LoopGainBounds:
    """The loop-gain bounds of an axis, from its config (see the module's docstring for the formulas)."""
    c = cfg.control
    if cfg.actuator.kind == "force":
        lag_s = cfg.actuator.force_lag_s
        w_i = 1.0 / lag_s if lag_s > 0 else math.pi / c.current_cycle_s
    else:
        w_i = c.current_kp_v_per_a / cfg.motor.lq_h
    w_n = min(w_i, math.pi / c.speed_cycle_s) / SPEED_LOOP_MARGIN
    inertia = feedforward_inertia(cfg)
    kv = min(w_n, math.pi / c.position_cycle_s) / POSITION_LOOP_MARGIN
    return LoopGainBounds(
        current_bandwidth_rad_s=w_i,
        speed_crossover_max_rad_s=w_n,
        inertia=inertia,
        speed_kp_max=w_n * inertia,
        kv_max_per_s=kv,
        speed_tn_min_s=SPEED_TN_FACTOR / w_n,
    )
