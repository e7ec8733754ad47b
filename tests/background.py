"""Expensive, pure computations of the suite, run in the background on CPU time nobody else wants.

Most of the suite is paced by the wall clock (a drive served at 1 ms SYNC, a master waiting for its
answers), so one of the two cores is idle for most of the run. The few computations that take minutes (the
gap bench's quick cases, a joint refit, the solve_ivp reference of the plant) are started at collection time
in one subprocess at ``SCHED_IDLE`` priority: the scheduler runs it only when no other task wants a CPU, and a
waking test preempts it at once, so it takes nothing from the timing tests. The tests that need a result are
moved to the end of the run and wait for it (:func:`result`); what they assert is unchanged, only where the
computation ran.

A job is a module-level function ``name`` in this file taking the folder it may write to and returning a
picklable result. A test asks for it with ``background.result(request.config, "name")``; the conftest starts
the jobs its selected tests declare with ``@pytest.mark.background("name", ...)``.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent


# ---------------------------------------------------------------------------------------------- the jobs
def quick_bench(out: Path) -> dict:
    """The gap bench's quick cases (tests/test_diagnosis_bench.py)."""
    from virtualaxis.diagnosis.bench import run_bench

    return run_bench(out, seed=3, quick=True, jobs=2)


def withheld_pair(out: Path) -> dict:
    """Backlash + Coulomb friction withheld together (tests/test_diagnosis_bench.py); the per-case report is
    read from ``out``."""
    from virtualaxis.diagnosis.bench import run_bench

    return {"bench": run_bench(out, seed=3, case_names=["backlash+coulomb"], quick=True, jobs=2), "out": out}


def plant_reference(out: Path) -> dict:
    """The compiled kernel and the independent solve_ivp reference on one command with every effect on
    (tests/test_plant_reference.py)."""
    sys.path.insert(0, str(HERE))
    from test_plant_reference import every_effect_config, reference_command

    from virtualaxis.sim.batch import simulate_command
    from virtualaxis.sim.reference import ReferenceAxis

    cfg = every_effect_config()
    t, p, v, a = reference_command()
    kern = simulate_command(cfg, t, p, vel_cmd_m_s=v, acc_cmd_m_s2=a)
    ref = ReferenceAxis(cfg, rtol=1e-8, atol=1e-12).run(t, p, v, a)
    keep = ("pos_cmd", "pos_meas")
    return {"kernel": {k: np.asarray(kern[k]) for k in keep}, "reference": {k: np.asarray(ref[k]) for k in keep}}


def _main_captured(argv: list[str]) -> tuple[int, str, str]:
    """``virtualaxis`` CLI in this process: exit status, stdout, stderr."""
    import contextlib
    import io

    from virtualaxis.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def rigid_force_diagnosis(out: Path) -> dict:
    """``virtualaxis diagnose`` on the gap bench's rigid-coulomb case (seed 5, quick), one job
    (tests/test_diagnosis_bench.py reads the report from ``out / "diag"``)."""
    from virtualaxis.diagnosis.bench import all_cases, generate_case

    case = next(c for c in all_cases() if c.name == "rigid-coulomb")
    meta = generate_case(case, out / "case", seed=5, quick=True)
    rc, text, err = _main_captured(["diagnose", "--config", str(out / "case" / "nominal.toml"), *meta["files"]["fit"],
                                    "--holdout", *meta["files"]["holdout"], "--out", str(out / "diag"),
                                    "--jobs", "1"])
    return {"rc": rc, "stdout": text, "stderr": err, "out": out / "diag"}


def dask_vs_pool(out: Path) -> dict:
    """The rigid-coulomb case diagnosed on a local Dask cluster (worker processes, 127.0.0.1) and on the
    process pool (tests/test_diagnosis_dask.py)."""
    from distributed import LocalCluster
    from distributed.diagnostics.plugin import SchedulerPlugin

    from virtualaxis.diagnosis.bench import all_cases, generate_case

    class CountFits(SchedulerPlugin):
        def __init__(self, owner):
            self.owner = owner

        def transition(self, key, start, finish, *args, **kwargs):
            if finish == "memory" and str(key).startswith("_safe_fit"):
                self.owner["done_fits"] += 1

    case = next(c for c in all_cases() if c.name == "rigid-coulomb")
    meta = generate_case(case, out / "case", seed=5, quick=True)
    common = ["diagnose", "--config", str(out / "case" / "nominal.toml"), *meta["files"]["fit"],
              "--holdout", *meta["files"]["holdout"], "--no-hybrid"]
    res: dict = {"done_fits": 0, "out": out}
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None, silence_logs=40)
    try:
        cluster.scheduler.add_plugin(CountFits(res), name="count-fits")
        res["scheduler_address"] = cluster.scheduler_address
        res["dask"] = _main_captured([*common, "--out", str(out / "dask"), "--scheduler",
                                      cluster.scheduler_address])
    finally:  # the default close timeout is a few seconds; a busy machine's worker processes may need more
        cluster.close(timeout=120)
    res["pool"] = _main_captured([*common, "--out", str(out / "pool"), "--jobs", "2"])
    return res


def reference_case_cli(out: Path) -> dict:
    """``virtualaxis gap-bench --suite reference --quick`` on one case (tests/test_diagnosis_gapbench.py): each
    case runs ``virtualaxis diagnose`` in a subprocess, as a user runs it."""
    rc, text, err = _main_captured(["gap-bench", "--suite", "reference", "--quick", "--cases",
                                    "rigid_pp/coulomb_friction", "--out", str(out), "--jobs", "2"])
    return {"rc": rc, "stdout": text, "stderr": err, "out": out}


def wrong_controller_diagnosis(out: Path) -> dict:
    """The diagnosis of P/P traces with a P/PI controller in the config, clean and with Coulomb friction
    (tests/test_diagnosis_controller.py): the two reports and the calibrated axis' controller."""
    sys.path.insert(0, str(HERE))
    from test_diagnosis_controller import RIGID, make_pp_traces

    from virtualaxis.config import load_axis_config
    from virtualaxis.diagnosis.pipeline import run_diagnosis

    traces = make_pp_traces(out)
    cfg = load_axis_config(RIGID)
    clean = run_diagnosis(cfg, traces["clean"][:2], traces["clean"][2:], jobs=1, hybrid=False).report
    result = run_diagnosis(cfg, traces["coulomb"][:2], traces["coulomb"][2:], jobs=1, hybrid=False)
    cal = result.calibrated.control
    return {"clean": clean, "coulomb": result.report,
            "calibrated": {"kv_1_per_s": cal.kv_1_per_s, "kv_per_s": cal.kv_per_s, "speed_ti_s": cal.speed_ti_s,
                           "velocity_kp_n_s_per_m": cal.velocity_kp_n_s_per_m}}


def _in_test_module(module: str, function: str, doc: str):
    """A job that is ``function(out)`` of a test module: the computation stays beside the assertions on it."""

    def job(out: Path) -> dict:
        import importlib

        sys.path.insert(0, str(HERE))
        return getattr(importlib.import_module(module), function)(out)

    job.__doc__ = f"{doc} (tests/{module}.py)"
    return job


#: jobs that are a test module's function: name -> (module, function, what it computes)
MODULE_JOBS = {
    "door_pair_runs": ("test_diagnosis_door", "run_pair",
                       "``virtualaxis diagnose`` on a friction pair, in a log and on a terminal"),
    "diagnose_friction_pair": ("test_diagnosis_pair", "diagnose_pair",
                               "Coulomb + viscous friction from a mass-only config"),
    "simulate_then_diagnose": ("test_diagnosis_door", "simulate_then_diagnose",
                               "``virtualaxis simulate`` traces diagnosed against their own config"),
    "diagnose_delayed": ("test_diagnosis_timing", "diagnose_delayed",
                         "a clean trace of a delayed controller stated in the config"),
    "diagnose_circle": ("test_diagnosis_contour", "diagnose_circle", "the contour error of two circles"),
    "beyond_the_end_stops": ("test_diagnosis_door", "beyond_the_end_stops",
                             "traces beyond the model's end stops, refused"),
    "every_option_runs": ("test_plant_vocab", "every_option_runs",
                          "the kernel and the solve_ivp reference with every plant option on"),
    "speed_loop_at_the_traces_rate": ("test_diagnosis_controller", "speed_loop_at_the_traces_rate",
                                      "a config's 8 kHz speed loop run at the traces' 1 kHz"),
    "start_at_rest_runs": ("test_plant_reset_kinematic", "start_at_rest_runs",
                           "the kernel and the solve_ivp reference holding with every kinematic effect"),
    "every_shipped_config": ("test_fmu", "every_shipped_config",
                             "an FMU of every shipped config, built, validated and run by FMPy"),
    "rcsa_json_and_plots": ("test_rcsa_cli", "rcsa_json_and_plots",
                            "``virtualaxis rcsa`` with JSON, plots and the FE check"),
}
globals().update({name: _in_test_module(*spec) for name, spec in MODULE_JOBS.items()})

JOBS = ("quick_bench", "withheld_pair", "plant_reference", "rigid_force_diagnosis", "dask_vs_pool",
        "reference_case_cli", "wrong_controller_diagnosis", *MODULE_JOBS)

#: Jobs that must never be stopped by :func:`pause`: a Dask cluster's scheduler, nanny and workers watch each
#: other with wall-clock timeouts, and a SIGSTOP of a minute or more makes them fire (seen in CI: the cluster's
#: close raised ``TimeoutError`` after its processes had been stopped). They run first; while one runs, the
#: file ``UNPAUSABLE_MARK`` exists and :func:`pause` waits for it to go instead of stopping the group.
UNPAUSABLE = ("dask_vs_pool",)
UNPAUSABLE_MARK = "running-unpausable"


# ---------------------------------------------------------------------------------------------- the runner
def _watch(session_pid: int) -> None:
    """Thread of the runner: when the session's main process is gone (ended, or killed without a chance to clean
    up), kill the runner's whole process group (its pool workers too)."""
    while True:
        time.sleep(1.0)
        try:
            os.kill(session_pid, 0)
        except ProcessLookupError:
            os.killpg(0, signal.SIGKILL)


def _run(names: list[str], folder: Path, session_pid: int) -> int:
    """Child process: each job in turn; ``<name>.pkl`` when done, ``<name>.err`` with the traceback if it
    raised (written under a temporary name and renamed, so a waiting test never reads half a file)."""
    import threading

    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(19)
    threading.Thread(target=_watch, args=(session_pid,), daemon=True).start()
    names = sorted(names, key=lambda n: n not in UNPAUSABLE)  # the unpausable ones first (stable otherwise)
    for name in names:
        if name not in UNPAUSABLE:
            (folder / UNPAUSABLE_MARK).unlink(missing_ok=True)
        out = folder / name
        out.mkdir(parents=True, exist_ok=True)
        try:
            value = globals()[name](out)
            data, suffix = pickle.dumps(value), ".pkl"
        except BaseException:  # reported to the test that waits for it
            data, suffix = traceback.format_exc().encode(), ".err"
        tmp = folder / f"{name}{suffix}.part"
        tmp.write_bytes(data)
        tmp.rename(folder / f"{name}{suffix}")
    (folder / UNPAUSABLE_MARK).unlink(missing_ok=True)
    return 0


class Runner:
    """The session's one runner process, as every process of the session (the pytest-xdist workers, or the
    single pytest process) sees it: its pid (also its process group), its folder and the jobs it runs."""

    def __init__(self, pid: int, folder: Path, names: set[str]) -> None:
        self.pid, self.folder, self.names = pid, folder, names

    def alive(self) -> bool:
        try:
            state = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            return False
        return state not in ("Z", "X")

    def signal_group(self, sig: int) -> bool:
        try:
            os.killpg(self.pid, sig)
        except ProcessLookupError:
            return False
        return True


RUNNER_KEY = pytest.StashKey[Runner]()


def _folder(shared: Path) -> Path:
    return shared / "background"


def start(config, shared: Path, session_pid: int, names: list[str]) -> None:
    """Start the jobs ``names`` in one SCHED_IDLE subprocess, once per session: the first process of the session
    to ask starts it, the others (pytest-xdist workers collecting the same tests) find it in ``shared``."""
    import fcntl

    if not names:
        return
    folder = _folder(shared)
    folder.mkdir(parents=True, exist_ok=True)
    with open(shared / "background.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        pid_file = folder / "runner.pid"
        if not pid_file.exists():
            if any(n in UNPAUSABLE for n in names):  # made before the runner exists, so no pause slips in first
                (folder / UNPAUSABLE_MARK).touch()
            with open(folder / "stderr.txt", "wb") as err:
                proc = subprocess.Popen([sys.executable, str(Path(__file__)), str(folder), str(session_pid), *names],
                                        stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
                                        cwd=str(HERE.parent))
            pid_file.write_text(f"{proc.pid}\n" + "\n".join(names))
        pid, *started = pid_file.read_text().split("\n")
    config.stash[RUNNER_KEY] = Runner(int(pid), folder, set(started))


def _runner(config) -> Runner | None:
    return config.stash.get(RUNNER_KEY, None)


def stop(shared: Path) -> None:
    """Kill the runner and its pool workers if they still run (end of session, from its main process)."""
    pid_file = _folder(shared) / "runner.pid"
    if not pid_file.exists():
        return
    runner = Runner(int(pid_file.read_text().split("\n")[0]), _folder(shared), set())
    if runner.alive():
        runner.signal_group(signal.SIGKILL)
    t_end = time.monotonic() + 10
    while runner.alive() and time.monotonic() < t_end:
        time.sleep(0.05)


def pause(config, wait_unpausable_s: float = 900.0) -> bool:
    """Stop the runner and its workers (SIGSTOP to its process group) while a timing-sensitive test runs: even
    at SCHED_IDLE a busy second core costs such a test (seen: the lockstep conformance suite failed 1 of 4 runs
    beside three SCHED_IDLE busy loops, 0 of 4 without). While an :data:`UNPAUSABLE` job runs, waits for it to
    finish first (it runs first and takes about a minute). Returns whether anything was paused. Only one test
    of the session pauses at a time (an ``exclusive`` test holds the session lock)."""
    runner = _runner(config)
    if runner is None or not runner.alive():
        return False
    mark, t_end = runner.folder / UNPAUSABLE_MARK, time.monotonic() + wait_unpausable_s
    while mark.exists() and runner.alive() and time.monotonic() < t_end:
        time.sleep(0.05)
    if not runner.alive():
        return False
    return runner.signal_group(signal.SIGSTOP)


def resume(config) -> None:
    runner = _runner(config)
    if runner is not None:
        runner.signal_group(signal.SIGCONT)


def result(config, name: str, timeout_s: float = 1800.0):
    """The result of job ``name``: waits for the runner (which runs at full speed once the tests before
    it are done); the job's own traceback if it raised."""
    runner = _runner(config)
    if runner is None or name not in runner.names:
        raise RuntimeError(f"background job {name!r} was not started (mark the test "
                           f"@pytest.mark.background({name!r}))")
    folder = runner.folder
    done, failed = folder / f"{name}.pkl", folder / f"{name}.err"
    t0 = time.monotonic()
    t_end = t0 + timeout_s
    while not done.exists() and not failed.exists():
        if not runner.alive() and not done.exists() and not failed.exists():
            err = (folder / "stderr.txt").read_text(errors="replace")[-4000:]
            raise RuntimeError(f"background runner ended before {name!r}:\n{err}")
        if time.monotonic() > t_end:
            raise TimeoutError(f"background job {name!r} not done after {timeout_s:.0f} s")
        time.sleep(0.05)
    WAITED_S[name] = WAITED_S.get(name, 0.0) + time.monotonic() - t0
    if failed.exists():
        raise RuntimeError(f"background job {name!r} raised:\n{failed.read_text()}")
    return pickle.loads(done.read_bytes())


#: seconds the tests waited for each job (the part of its computation the rest of the suite did not hide)
WAITED_S: dict[str, float] = {}


if __name__ == "__main__":
    sys.exit(_run(sys.argv[3:], Path(sys.argv[1]), int(sys.argv[2])))
