"""Cost of one FMU communication step (FMPy as the host) against the simulator's own step, measured in one run.

    python benchmarks/bench_fmu.py [--config configs/seed000-hust.toml] [--steps 2000] [--cycles-per-step 1]

Prints the wall time per step of: ``AxisSimulator.advance`` (baseline), ``advance`` + ``preview`` (what the FMU does
per step when its outputs are read) and the FMU through FMPy's FMU2Slave (set one input, doStep, read 10 outputs),
and their ratios to the baseline. Run it in a process of its own (it starts no subprocess after loading the FMU:
docs/fmu.md).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "seed000-hust.toml"))
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--cycles-per-step", type=int, default=1)
    args = ap.parse_args()

    import math

    from virtualaxis.config import load_axis_config
    from virtualaxis.sim.simulator import AxisSimulator

    cfg = load_axis_config(args.config)
    cyc = cfg.control.position_cycle_s
    k = args.cycles_per_step
    out = Path(tempfile.mkdtemp()) / "axis.fmu"
    subprocess.run([sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())",
                    "fmu", "--config", args.config, "--out", str(out), "--step", repr(k * cyc)], check=True,
                   capture_output=True)

    def setpoint(i: int) -> float:
        return 0.01 * math.sin(i * k * cyc * 2 * math.pi * 2)

    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.advance(10)  # warm
    t0 = time.perf_counter()
    for i in range(args.steps):
        sim.set_position_setpoint(setpoint(i))
        sim.advance(k)
    base = (time.perf_counter() - t0) / args.steps

    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.advance(10)
    t0 = time.perf_counter()
    for i in range(args.steps):
        sim.set_position_setpoint(setpoint(i))
        sim.preview()
        sim.advance(k)
    with_preview = (time.perf_counter() - t0) / args.steps

    import fmpy
    from fmpy.fmi2 import FMU2Slave

    md = fmpy.read_model_description(str(out))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    outputs = [vr[n] for n in ("pos_cmd", "pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas",
                               "current_q", "following_error", "table_position_m", "motor_speed_rad_s")]
    s = FMU2Slave(guid=md.guid, unzipDirectory=fmpy.extract(str(out)),
                  modelIdentifier=md.coSimulation.modelIdentifier, instanceName="bench")
    s.instantiate()
    s.setupExperiment(startTime=0.0)
    s.enterInitializationMode()
    s.exitInitializationMode()
    for i in range(10):
        s.doStep(i * k * cyc, k * cyc)
    t0 = time.perf_counter()
    for i in range(args.steps):
        s.setReal([vr["position_setpoint_m"]], [setpoint(i)])
        s.getReal(outputs)
        s.doStep((i + 10) * k * cyc, k * cyc)
    fmu = (time.perf_counter() - t0) / args.steps
    s.terminate()
    s.freeInstance()

    print(f"config {args.config}, {args.steps} steps of {k} position cycle(s) ({k * cyc * 1e3:g} ms)")
    for name, v in (("AxisSimulator.advance (baseline)", base), ("advance + preview", with_preview),
                    ("FMU via FMPy: setReal + getReal(10) + doStep", fmu)):
        print(f"  {name:46s} {v * 1e6:9.1f} us/step  x{v / base:5.2f}  real-time factor {k * cyc / v:7.1f}")


if __name__ == "__main__":
    main()
