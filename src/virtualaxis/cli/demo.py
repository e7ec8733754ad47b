"""``virtualaxis demo``: a live CSP move of the virtual drive under a real CANopen master.

The drive (seed 000 axis, node 1) and a ``canopen`` master run in this process on a host-local python-can
``virtual`` bus, in SYNC lockstep (every SYNC advances the plant by one 1 ms communication cycle, so the
result does not depend on the machine's load). The master configures the PDOs by SDO (synchronous RPDO with
controlword + target position, synchronous TPDOs with statusword, position, following error and torque),
switches to cyclic synchronous position mode, enables the drive through the CiA 402 state machine and
streams a jerk-limited move of +-100 mm at 12 m/min, one target per SYNC, paced to the wall clock.

A live readout shows position and following error; at the end the demo writes a plot (PNG) and a summary
(JSON) to ``--out`` and checks the following error the master received against the plant simulator
(``virtualaxis.sim``) run offline on the same set-points.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np


def register(sub) -> None:
    p = sub.add_parser("demo", help="live CSP move of the virtual CiA 402 drive under a CANopen master")
    p.add_argument("--config", default=None, help="axis config (default configs/seed000-hust.toml)")
    p.add_argument("--out", default="virtualaxis-demo", help="output directory for the plot and the JSON")
    p.add_argument("--stroke-mm", type=float, default=100.0, help="move distance [mm] (default 100)")
    p.add_argument("--feed-m-min", type=float, default=12.0, help="feed rate [m/min] (default 12)")
    p.add_argument("--no-pace", action="store_true", help="send SYNC as fast as possible (not every 1 ms)")
    p.set_defaults(func=run)


def s_curve(distance_m: float, v_max: float, a_max: float, j_max: float, dt: float) -> np.ndarray:
    """Jerk-limited point-to-point positions sampled every dt (trapezoid smoothed by a moving average)."""
    n_j = max(1, int(round(a_max / j_max / dt)))
    t_acc = v_max / a_max
    if distance_m < v_max * t_acc:  # triangular
        v_max = math.sqrt(distance_m * a_max)
        t_acc = v_max / a_max
    t_const = distance_m / v_max - t_acc
    n = int(math.ceil((2 * t_acc + t_const) / dt)) + 1
    t = np.arange(n) * dt
    v = np.minimum(np.minimum(a_max * t, v_max), np.maximum(a_max * (2 * t_acc + t_const - t), 0.0))
    x = np.concatenate([[0.0], np.cumsum(v[:-1]) * dt])
    x *= distance_m / x[-1]
    x = np.concatenate([x, np.full(n_j, distance_m)])
    kernel = np.ones(n_j) / n_j
    xp = np.concatenate([np.zeros(n_j - 1), x])
    return np.convolve(xp, kernel, mode="valid")


def run(args) -> int:
    from canopen.nmt import NmtError
    from canopen.sdo.exceptions import SdoError

    from virtualaxis.cli.main import CliError
    from virtualaxis.config import load_axis_config
    from virtualaxis.drive.commissioning import commissioned_travel_m, switch_positions_m
    from virtualaxis.drive.settings import drive_settings
    from virtualaxis.runtime.axes import DEFAULT_CONFIG

    cfg = load_axis_config(args.config or DEFAULT_CONFIG)
    max_mm = 1000 * commissioned_travel_m(cfg, switch_positions_m(cfg, drive_settings(cfg)))[1]
    if not 0 < args.stroke_mm <= max_mm:
        raise CliError(f"--stroke-mm must be in (0, {max_mm:g}] for {cfg.axis.name}: the drive's software position "
                       f"limit 0x607D:2 (limits.travel_max_m, kept inside the limit switch)")
    if not 0 < args.feed_m_min <= cfg.limits.max_velocity_m_s * 60:
        raise CliError(f"--feed-m-min must be in (0, {cfg.limits.max_velocity_m_s * 60:g}] (limits.max_velocity_m_s)")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"{out}: cannot create output directory ({exc.strerror})") from None
    from virtualaxis.cli.outputs import staged_dir

    t_start = time.perf_counter()
    # (the plot and the summary of each run replace the last run's together, once both are complete)
    with staged_dir(out) as stage:
        try:
            result = run_demo(cfg, stage, args.stroke_mm * 1e-3, args.feed_m_min / 60.0, pace=not args.no_pace)
        except (RuntimeError, SdoError, NmtError) as exc:
            raise CliError(f"demo: {exc}") from None
        result["wall_time_s"] = time.perf_counter() - t_start
        (stage / "demo_summary.json").write_text(json.dumps(result, indent=2))
    print(f"\nwrote {out / 'demo_csp_move.png'} and {out / 'demo_summary.json'} ({result['wall_time_s']:.1f} s)")
    print(
        f"max |following error| {result['max_abs_following_error_um']:.1f} um at "
        f"{result['feed_m_min']:g} m/min (Kv = {result['kv_1000_per_min']:.2f} (1000/min): v/Kv = "
        f"{result['steady_state_following_error_expected_um']:.1f} um); drive vs offline simulation: "
        f"max difference {result['offline_match']['max_abs_difference_um']:.2f} um"
    )
    return 0


def run_demo(cfg, out: Path, stroke_m: float, v_max: float, pace: bool = True) -> dict:
    import os

    import canopen

    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.runtime import AxisNode, Runtime, open_bus

    channel = f"virtualaxis-demo-{os.getpid()}"
    bus = open_bus(f"virtual:{channel}")
    axis = AxisNode(bus, 1, cfg, name="X")
    runtime = Runtime(bus, [axis], lockstep=True).start()
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    try:
        node = canopen.BaseNode402(1, str(DEFAULT_EDS))
        net.add_node(node)
        print("demo: master found node 1, configuring PDOs by SDO ...", flush=True)
        node.sdo[0x1017].raw = 100  # heartbeat 100 ms
        node.nmt.wait_for_heartbeat(2.0)
        node.sdo[0x1006].raw = 1000  # communication cycle 1 ms
        node.sdo[0x60C2][1].raw = 1  # interpolation period 1 x 10^-3 s
        node.sdo[0x60C2][2].raw = -3
        # following error window: without feed-forward the lag is v / Kv (1.7 mm at 12 m/min, Kv 7.2)
        node.sdo[0x6065].raw = 5000
        node.tpdo.read()
        node.rpdo.read()
        # RPDO2: controlword + target position, synchronous; TPDO2: statusword + position, TPDO4: FE + torque
        node.rpdo[2].trans_type = 1
        node.tpdo[2].trans_type = 1
        node.tpdo[4].trans_type = 1
        node.tpdo[4].enabled = True
        for pdo in (node.rpdo[2], node.tpdo[2], node.tpdo[4]):
            pdo.save()
        node.setup_402_state_machine(read_pdos=False)
        node.sdo[0x6060].raw = 8  # cyclic synchronous position
        node.nmt.state = "OPERATIONAL"
        time.sleep(0.05)
        dt = axis.drive.cycle_s
        unit = axis.drive.scaling.metres_per_unit
        x0_units = node.sdo[0x6064].raw
        rpdo = node.rpdo[2]
        rpdo["Target position"].raw = x0_units
        rpdo["Controlword"].raw = 0x06

        def sync_step(cw: int, target_units: int) -> None:
            rpdo["Controlword"].raw = cw
            rpdo["Target position"].raw = target_units
            rpdo.transmit()
            net.sync.transmit()
            if node.tpdo[4].wait_for_reception(2.0) is None:
                raise RuntimeError("no TPDO answered the SYNC")

        for cw in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation (one SYNC each + settle)
            for _ in range(5):
                sync_step(cw, x0_units)
        state = node.sdo[0x6041].raw
        if state & 0x6F != 0x27:
            raise RuntimeError(f"drive did not reach OPERATION ENABLED (statusword 0x{state:04X})")
        a_max = min(2.0, cfg.limits.max_acceleration_m_s2)
        move = s_curve(stroke_m, v_max, a_max, 40.0, dt)
        dwell = np.full(int(0.3 / dt), stroke_m)
        path_m = np.concatenate([np.zeros(int(0.1 / dt)), move, dwell, stroke_m - move, np.zeros(int(0.3 / dt))])
        targets_units = np.round(x0_units + path_m / unit).astype(np.int64)
        n = len(targets_units)
        fe_units = np.zeros(n, dtype=np.int64)
        pos_units = np.zeros(n, dtype=np.int64)
        torque_pm = np.zeros(n, dtype=np.int64)
        print(f"demo: CSP move {stroke_m * 1e3:g} mm at {v_max * 60:g} m/min, {n} SYNC cycles of {dt * 1e3:g} ms")
        t0 = time.perf_counter()
        last_print = 0.0
        tty = sys.stdout.isatty()
        for k in range(n):
            sync_step(0x0F, int(targets_units[k]))
            fe_units[k] = node.tpdo[4]["Following error actual value"].raw
            torque_pm[k] = node.tpdo[4]["Torque actual value"].raw
            pos_units[k] = node.tpdo[2]["Position actual value"].raw
            now = time.perf_counter() - t0
            if now - last_print > (0.05 if tty else 0.5) or k == n - 1:
                last_print = now
                sys.stdout.write(
                    ("\r" if tty else "")
                    + f"  t = {k * dt:6.3f} s   target = {(targets_units[k] - x0_units) * unit * 1e3:8.3f} mm   "
                    f"actual = {(pos_units[k] - x0_units) * unit * 1e3:8.3f} mm   "
                    f"following error = {fe_units[k] * unit * 1e6:8.1f} um   torque = {torque_pm[k] / 10:6.1f} %"
                    + ("" if tty else "\n")
                )
                sys.stdout.flush()
            if pace:
                ahead = (k + 1) * dt - (time.perf_counter() - t0)
                if ahead > 0:
                    time.sleep(ahead)
        for _ in range(5):
            sync_step(0x06, int(targets_units[-1]))
        statusword = node.sdo[0x6041].raw
    finally:
        net.disconnect()
        runtime.stop()
        bus.shutdown()
    sync_stats = runtime.stats.as_dict()
    offline_fe_units = _offline_following_error(cfg, targets_units, unit, dt, axis.drive)
    diff_units = fe_units - offline_fe_units
    t = np.arange(n) * dt
    fe_m = fe_units * unit
    kv = axis.drive.get_parameter("kv_1000_per_min")
    kv_1_s = kv * 1000.0 / 60.0
    _plot(
        out / "demo_csp_move.png",
        t,
        (targets_units - x0_units) * unit,
        (pos_units - x0_units) * unit,
        fe_m,
        offline_fe_units * unit,
        torque_pm / 10.0,
        cfg.axis.name,
        v_max,
        kv,
    )
    return {
        "axis": cfg.axis.name,
        "config": str(cfg.path),
        "bus": "python-can virtual (in-process), SYNC lockstep",
        "cycles": int(n),
        "cycle_s": dt,
        "stroke_m": stroke_m,
        "feed_m_min": v_max * 60,
        "kv_1000_per_min": kv,
        "max_abs_following_error_um": float(np.max(np.abs(fe_m)) * 1e6),
        "rms_following_error_um": float(np.sqrt(np.mean(fe_m**2)) * 1e6),
        "steady_state_following_error_expected_um": v_max / kv_1_s * 1e6,
        "final_position_error_um": float((pos_units[-1] - targets_units[-1]) * unit * 1e6),
        "max_abs_torque_percent": float(np.max(np.abs(torque_pm)) / 10.0),
        "offline_match": {
            "description": "0x60F4 from the TPDO vs AxisSimulator run on the drive's set-points, in position units",
            "max_abs_difference_um": float(np.max(np.abs(diff_units)) * unit * 1e6),
            "cycles_differing": int(np.count_nonzero(diff_units)),
        },
        "final_statusword": f"0x{statusword:04X}",
        "runtime": sync_stats,
    }


def _offline_following_error(cfg, targets_units: np.ndarray, unit: float, dt: float, drive) -> np.ndarray:
    """The plant simulator alone, fed the set-points the drive applies: the target sent before SYNC k
    drives the cycle after SYNC k (interpolation period = one cycle), velocity feed-forward = its slope."""
    from virtualaxis.sim import AxisSimulator, ControlMode

    sim = AxisSimulator(cfg, initial_position_m=0.0)
    for key in ("P_KV", "P_KFF", "P_KTFF", "P_KPW", "P_TIW", "P_ILIM"):  # the drive's loop parameters
        from virtualaxis.sim import layout as L

        sim.pr[getattr(L, key)] = drive.sim.pr[getattr(L, key)]
    sim.set_mode(ControlMode.POSITION)
    sim.enable(True)
    n = len(targets_units)
    out = np.zeros(n, dtype=np.int64)
    x = targets_units.astype(float) * unit
    prev, prev_v = x[0], 0.0
    for k in range(n):
        # the set-point of this cycle is the target that arrived with the previous SYNC
        sp = x[k - 1] if k >= 1 else x[0]
        v = (sp - prev) / dt
        sim.set_position_setpoint(sp, v, (v - prev_v) / dt)
        prev, prev_v = sp, v
        sim.advance(1)
        out[k] = int(round(sim.state.following_error_m / unit))
    return out


def _plot(path: Path, t, target_m, actual_m, fe_m, fe_offline_m, torque_pct, name: str, v: float, kv: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    axs[0].plot(t, target_m * 1e3, label="target (RPDO)")
    axs[0].plot(t, actual_m * 1e3, "--", label="actual 0x6064 (TPDO)")
    axs[0].set_ylabel("position [mm]")
    axs[0].legend(loc="best")
    axs[1].plot(t, fe_m * 1e6, label="0x60F4 from the drive (TPDO)")
    axs[1].plot(t, fe_offline_m * 1e6, ":", label="virtualaxis.sim offline")
    axs[1].axhline(v / (kv * 1000 / 60) * 1e6, color="grey", lw=0.8, label="v / Kv")
    axs[1].axhline(-v / (kv * 1000 / 60) * 1e6, color="grey", lw=0.8)
    axs[1].set_ylabel("following error [um]")
    axs[1].legend(loc="best")
    axs[2].plot(t, torque_pct)
    axs[2].set_ylabel("torque 0x6077 [% rated]")
    axs[2].set_xlabel("time [s]")
    fig.suptitle(f"{name}: CSP move under SYNC (1 ms), CANopen master <-> virtual CiA 402 drive")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
