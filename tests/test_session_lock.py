"""The session lock of the test suite (tests/session_lock.py) across processes, as pytest-xdist workers use it."""

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

HOLD = """
import sys, time
sys.path.insert(0, {here!r})
from pathlib import Path
from session_lock import SessionLock
lock = SessionLock(Path({folder!r}))
with getattr(lock, {side!r})():
    print("in", time.monotonic(), flush=True)
    time.sleep({hold_s})
print("out", time.monotonic(), flush=True)
"""


def _hold(folder: Path, side: str, hold_s: float) -> subprocess.Popen:
    code = HOLD.format(here=str(HERE), folder=str(folder), side=side, hold_s=hold_s)
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)


def _times(proc: subprocess.Popen) -> tuple[float, float]:
    out, _ = proc.communicate(timeout=30)
    lines = dict(line.split() for line in out.splitlines())
    return float(lines["in"]), float(lines["out"])


def _entered(proc: subprocess.Popen) -> float:
    line = proc.stdout.readline().split()
    assert line[0] == "in"
    return float(line[1])


def test_shared_holders_overlap_and_an_exclusive_holder_runs_alone(tmp_path):
    a = _hold(tmp_path, "shared", 1.0)
    a_in = _entered(a)
    b = _hold(tmp_path, "shared", 1.0)
    b_in = _entered(b)
    assert b_in < a_in + 0.9  # two shared holders at once
    x = _hold(tmp_path, "exclusive", 0.5)
    a.wait(timeout=30)
    b.wait(timeout=30)
    x_in, x_out = _times(x)
    assert x_in >= max(a_in, b_in) + 0.9  # waited for both shared holders


def test_a_waiting_exclusive_holder_is_not_starved_by_new_shared_ones(tmp_path):
    a = _hold(tmp_path, "shared", 1.5)
    _entered(a)
    x = _hold(tmp_path, "exclusive", 0.5)
    time.sleep(0.3)  # x now waits for a
    late = _hold(tmp_path, "shared", 0.1)  # arrives after x: must wait for x to finish
    x_in, x_out = _times(x)
    late_in, _ = _times(late)
    a.wait(timeout=30)
    assert late_in >= x_out - 0.05
