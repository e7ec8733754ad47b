"""FMPy as the FMI host of tests/test_fmu.py, in a child process: ``python tests/fmu_host.py JOB.json``.

The FMU runs in a process of its own, as in a user's script (FMPy loads and unloads the FMU's binary as it does
by default), so that the test sees the host's exit status. The job (JSON) names what to run; results go to
``job["out"]`` (.npz).
"""

from __future__ import annotations

import json
import sys

import fmpy
import numpy as np
from fmpy import calloc, free
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)

#: the callbacks of the instances made here (module level: ctypes callbacks must outlive the instances)
CALLBACKS: list = []


def simulate(job: dict) -> dict:
    """fmpy.simulate_fmu with the inputs given at the communication points (and held over each step)."""
    t = np.asarray(job["time"], float)
    signals = job["inputs"]
    sig = np.zeros(len(t), dtype=[("time", float)] + [(k, float) for k in signals])
    sig["time"] = t
    for k, v in signals.items():
        sig[k] = v
    res = fmpy.simulate_fmu(job["fmu"], stop_time=float(t[-1]), step_size=job["step_s"],
                            output_interval=job["step_s"], input=sig, start_values=job.get("start_values", {}))
    return {name: res[name] for name in res.dtype.names}


def _slave(job: dict, md, unzipped: str, messages: list[str]) -> FMU2Slave:
    def logger(_env, _name, _status, _category, message):
        messages.append(message.decode(errors="replace"))

    callbacks = fmi2CallbackFunctions()
    callbacks.logger = fmi2CallbackLoggerTYPE(logger)
    callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
    callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
    CALLBACKS.append((callbacks, logger))
    s = FMU2Slave(guid=md.guid, unzipDirectory=unzipped, modelIdentifier=md.coSimulation.modelIdentifier,
                  instanceName="test")
    s.instantiate(callbacks=callbacks, loggingOn=True)
    s.setupExperiment(startTime=0.0)
    s.enterInitializationMode()
    return s


def cosim(job: dict) -> dict:
    """A position controller here drives the speed-interface FMU, one position cycle per step: speed set-point
    = Kv (command - position feedback) + velocity_ff_factor x speed feed-forward, as the drive's position loop."""
    md = fmpy.read_model_description(job["fmu"])
    vr = {v.name: v.valueReference for v in md.modelVariables}
    cmd, vff = np.asarray(job["cmd"]), np.asarray(job["vff"])
    kv, kff, cyc = job["kv_1_per_s"], job["kff"], job["cycle_s"]
    messages: list[str] = []
    s = _slave(job, md, fmpy.extract(job["fmu"]), messages)
    s.setReal([vr["initial_position_m"]], [float(cmd[0])])
    s.exitInitializationMode()
    n = len(cmd)
    fb, table = np.zeros(n), np.zeros(n)
    for i in range(n):
        fb[i], table[i] = s.getReal([vr["pos_fb"], vr["table_position_m"]])
        s.setReal([vr["velocity_setpoint_m_s"]], [kv * (cmd[i] - fb[i]) + kff * vff[i]])
        s.doStep(currentCommunicationPoint=i * cyc, communicationStepSize=cyc)
    s.terminate()
    s.freeInstance()
    return {"pos_fb": fb, "table_position_m": table}


def refusals(job: dict) -> dict:
    """Each case: start an instance, set parameters in initialisation, set inputs, step; which call failed and
    what the FMU logged. A case that passes records the following error at each step."""
    md = fmpy.read_model_description(job["fmu"])
    vr = {v.name: v.valueReference for v in md.modelVariables}
    unzipped = fmpy.extract(job["fmu"])
    out: dict = {}
    for k, case in enumerate(job["cases"]):
        messages: list[str] = []
        s = _slave(job, md, unzipped, messages)
        failed = ""
        fe = []
        try:
            failed = "setReal"
            for name, value in case.get("parameters", {}).items():
                s.setReal([vr[name]], [value])
            failed = "exitInitializationMode"
            s.exitInitializationMode()
            for i in range(case.get("steps", 1)):
                failed = "setReal"
                for name, value in case.get("inputs", {}).items():
                    s.setReal([vr[name]], [value])
                failed = "getReal"
                fe.append(s.getReal([vr["following_error"]])[0])
                failed = "doStep"
                s.doStep(currentCommunicationPoint=i * case["step_s"], communicationStepSize=case["step_s"])
            failed = ""
            s.terminate()
        except FMICallException:
            pass
        s.freeInstance()
        out[f"failed{k}"] = np.array(failed)
        out[f"log{k}"] = np.array("\n".join(messages))
        out[f"fe{k}"] = np.array(fe)
    return out


def smoke(job: dict) -> dict:
    """Each FMU: FMPy's validation, then a short run on its default inputs (all outputs finite)."""
    from fmpy.validation import validate_fmu

    out = {}
    for k, fmu in enumerate(job["fmus"]):
        out[f"problems{k}"] = np.array("\n".join(validate_fmu(fmu)))
        res = fmpy.simulate_fmu(fmu, stop_time=job["stop_s"])
        out[f"finite{k}"] = np.array(all(np.all(np.isfinite(res[n])) for n in res.dtype.names))
        out[f"rows{k}"] = np.array(len(res))
    return out


if __name__ == "__main__":
    with open(sys.argv[1], encoding="utf-8") as fh:
        job = json.load(fh)
    result = {"simulate": simulate, "cosim": cosim, "refusals": refusals, "smoke": smoke}[job["job"]](job)
    np.savez(job["out"], **result)
