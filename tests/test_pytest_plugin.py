"""The pytest plugin (virtualaxis.testing, pytest11 entry point) as a user runs it: pytest in a subprocess on
examples/gcode_contour (passes; fails with a mistuned Kv) and on a generated test file using the marker, the
udp transport, indirect parametrisation, the fault-injection API, and clean-up of the served process when a
test fails or the session is interrupted."""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _plugin_args() -> list[str]:
    """``-p virtualaxis.testing`` unless the installed package registers the pytest11 entry point already
    (pytest refuses the same plugin under two names)."""
    names = {ep.name for ep in importlib.metadata.entry_points(group="pytest11")}
    return [] if "virtualaxis" in names else ["-p", "virtualaxis.testing"]


def _pytest(args: list[str], cwd: Path, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    src = str(ROOT / "src")
    pythonpath = os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", *_plugin_args(),
                           *args], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHONPATH": pythonpath, **(env or {})})


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is not alive
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_gcode_example_passes_and_fails_with_a_mistuned_kv(tmp_path):
    """The user-style CI test: within 40 um with the drive's Kv; Kv 1.0 1000/min on X breaks the tolerance."""
    good, bad = tmp_path / "good.json", tmp_path / "bad.json"
    ok = _pytest(["examples/gcode_contour"], ROOT, {"GCODE_REPORT": str(good)})
    assert ok.returncode == 0, ok.stdout[-3000:] + ok.stderr[-2000:]
    fail = _pytest(["examples/gcode_contour"], ROOT, {"GCODE_REPORT": str(bad), "GCODE_KV_X": "1.0"})
    assert fail.returncode == 1, fail.stdout[-3000:] + fail.stderr[-2000:]
    assert "contour error" in fail.stdout and "> 40 um" in fail.stdout
    g, b = json.loads(good.read_text()), json.loads(bad.read_text())
    assert g["max_contour_error_um"] <= 40 < b["max_contour_error_um"]
    assert b["max_contour_error_um"] > 10 * g["max_contour_error_um"]


PLUGIN_TESTS = '''
import os
import pytest

PIDS = os.environ["VA_PID_FILE"]


def _record(axis):
    if axis.process is not None:
        with open(PIDS, "a") as f:
            f.write(f"{axis.process.pid}\\n")


@pytest.mark.virtual_axis(transport="udp")
def test_udp_master_and_fault_over_can(virtual_axis):
    _record(virtual_axis)
    assert virtual_axis.bus_spec.startswith("udp_multicast:") and virtual_axis.process.poll() is None
    assert virtual_axis.lockstep  # the default pacing: the drive advances one cycle per SYNC
    node = virtual_axis.node
    assert node.sdo[0x1000].raw == 0x00020192
    virtual_axis.inject("over_current")
    import time
    end = time.monotonic() + 5
    while node.sdo[0x603F].raw != 0x2310:
        assert time.monotonic() < end
        virtual_axis.sync(1)
    assert node.sdo[0x6041].raw & 0x4F == 0x08


@pytest.mark.parametrize("virtual_axis", [{"node_id": 3}, {"node_id": (5, 6), "pacing": "realtime"}], indirect=True)
def test_indirect_node_ids(virtual_axis):
    assert virtual_axis.node_ids in ((3,), (5, 6))
    assert virtual_axis.lockstep == (virtual_axis.node_ids == (3,))  # lockstep unless real time is asked for
    assert virtual_axis.runtime.lockstep == virtual_axis.lockstep
    for nid, node in virtual_axis.nodes.items():
        assert node.sdo[0x1018][1].raw is not None and node.id == nid


@pytest.mark.virtual_axis(pacing="lockstep")
def test_in_process_python_injection_api(virtual_axis):
    assert virtual_axis.transport == "virtual" and virtual_axis.lockstep
    cycles = virtual_axis.drives[1].counters["cycles"]
    virtual_axis.sync(5)
    import time
    end = time.monotonic() + 3
    while virtual_axis.drives[1].counters["cycles"] < cycles + 5 and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.05)
    assert virtual_axis.drives[1].counters["cycles"] == cycles + 5  # one cycle per SYNC, none without
    virtual_axis.injector.inject("encoder_loss")
    import time
    end = time.monotonic() + 5
    while virtual_axis.node.sdo[0x603F].raw != 0x7305:
        assert time.monotonic() < end
        virtual_axis.sync(1)


@pytest.mark.virtual_axis(node_id=1)
def test_basenode402_changes_state_between_syncs(virtual_axis):
    # (lockstep: the event-driven statusword TPDO must go out between SYNCs; canopen waits for it)
    node = virtual_axis.node
    node.setup_402_state_machine()
    node.nmt.state = "OPERATIONAL"
    node.op_mode = "PROFILED POSITION"
    virtual_axis.sync(10)
    node.state = "OPERATION ENABLED"
    assert node.state == "OPERATION ENABLED"
    node.state = "SWITCH ON DISABLED"


@pytest.mark.virtual_axis(transport="udp", allow_fault_injection=False)
def test_failing_test_still_cleans_up(virtual_axis):
    _record(virtual_axis)
    assert False, "deliberate failure"


@pytest.mark.virtual_axis(transport="udp")
def test_interrupted(virtual_axis):
    _record(virtual_axis)
    if os.environ.get("VA_INTERRUPT"):
        raise KeyboardInterrupt
'''


def test_plugin_fixture_markers_parametrisation_and_cleanup(tmp_path):
    (tmp_path / "test_user.py").write_text(textwrap.dedent(PLUGIN_TESTS))
    pids = tmp_path / "pids.txt"
    env = {"VA_PID_FILE": str(pids)}
    r = _pytest(["-k", "not interrupted", "test_user.py"], tmp_path, env)
    assert "1 failed, 5 passed" in r.stdout, r.stdout[-4000:] + r.stderr[-2000:]
    assert "deliberate failure" in r.stdout
    r = _pytest(["-k", "interrupted", "test_user.py"], tmp_path, {**env, "VA_INTERRUPT": "1"})
    assert r.returncode == 2 and "KeyboardInterrupt" in r.stdout + r.stderr, r.stdout[-3000:]
    served = [int(p) for p in pids.read_text().split()]
    assert len(served) == 3
    time.sleep(0.2)
    assert not [p for p in served if _alive(p)], "a served drive outlived its test"


KILLED_TEST = '''
import os
import time

import pytest


@pytest.mark.virtual_axis(transport="udp")
def test_runs_until_the_job_is_cancelled(virtual_axis):
    with open(os.environ["VA_PID_FILE"], "w") as fh:
        fh.write(str(virtual_axis.process.pid))
    time.sleep(120)
'''


def test_a_test_run_ended_by_sigterm_leaves_no_served_drive(tmp_path):
    """A CI job cancelled or timed out ends pytest with SIGTERM (or SIGKILL): no clean-up of pytest's runs, and
    the served drive must not live on."""
    import signal

    (tmp_path / "test_killed.py").write_text(KILLED_TEST)
    pids = tmp_path / "pid.txt"
    src = str(ROOT / "src")
    pythonpath = os.pathsep.join(p for p in (src, os.environ.get("PYTHONPATH", "")) if p)
    for sig in (signal.SIGTERM, signal.SIGKILL):
        pids.unlink(missing_ok=True)
        run = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider",
                                *_plugin_args(), "test_killed.py"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL,
                               env={**os.environ, "PYTHONPATH": pythonpath, "VA_PID_FILE": str(pids)})
        try:
            deadline = time.monotonic() + 120
            while not (pids.exists() and pids.read_text()):
                assert run.poll() is None and time.monotonic() < deadline, "the test never served its drive"
                time.sleep(0.1)
            served = int(pids.read_text())
            assert _alive(served)
            run.send_signal(sig)
            run.wait(30)
            deadline = time.monotonic() + 15
            while _alive(served) and time.monotonic() < deadline:
                time.sleep(0.1)
            assert not _alive(served), f"the served drive outlived pytest ended by {sig.name}"
        finally:
            if run.poll() is None:
                run.kill()


BAD_OPTION_TESTS = '''
import pytest


@pytest.mark.virtual_axis(lokstep=True)
def test_a_misspelt_option(virtual_axis):
    pass


@pytest.mark.virtual_axis(config="tuned_drive")
def test_a_config_that_is_no_preset(virtual_axis):
    pass


@pytest.mark.virtual_axis(node_id=200)
def test_a_node_id_out_of_range(virtual_axis):
    pass
'''


def test_a_bad_marker_option_is_one_line_naming_it_without_the_plugins_source(tmp_path):
    """A misspelt keyword, a config that is no file and no preset, a node id out of range: each test errors with
    one message saying what to write instead; no traceback into the plugin, no served drive started."""
    (tmp_path / "test_bad.py").write_text(textwrap.dedent(BAD_OPTION_TESTS))
    r = _pytest(["-rE", "test_bad.py"], tmp_path, timeout=120)
    out = r.stdout + r.stderr
    assert "3 error" in r.stdout, out[-4000:]
    assert "virtual_axis: unknown option 'lokstep' (did you mean lockstep?)" in out, out[-4000:]
    assert "or name a preset" in out and "tuned-drive" in out, out[-4000:]
    assert "node_id must be 1..127" in out, out[-4000:]
    assert "virtualaxis/testing.py" not in out, out[-4000:]
