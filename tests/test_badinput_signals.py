"""SIGINT / SIGTERM / SIGHUP / SIGQUIT during ``simulate``: the process exits 130 / 143 / 129 / 131 with one
line, the final path holds nothing (or its old content), and no temporary file is left. A subprocess, since
signals are the point."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from signal_defaults import default_terminal_signals

ROOT = Path(__file__).resolve().parents[1]
C4 = ROOT / "configs" / "seed004-siemens.toml"


def _run_and_signal(tmp_path: Path, sig: int, out: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # a long run (3600 s simulated: ~430 MB of trace, several seconds of writing even on a fast host) that is
    # certainly still writing when the signal comes
    proc = subprocess.Popen(
        [sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(C4), "--profile",
         "sine:stroke_mm=100,feed_mm_min=3000", "--duration", "3600", "--out", str(out), "--force"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
        preexec_fn=default_terminal_signals)
    deadline = time.monotonic() + 90
    # wait until the temporary trace has grown (the run is writing), then signal
    while time.monotonic() < deadline:
        parts = list(tmp_path.glob(".*partial*"))
        if parts and parts[0].stat().st_size > 200_000:
            break
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(sig)
    try:
        stdout, stderr = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)


@pytest.mark.timeout(180)
@pytest.mark.parametrize("sig,code,word", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted"),
                                            (signal.SIGHUP, 129, "terminated (SIGHUP)"),
                                            (signal.SIGQUIT, 131, "terminated (SIGQUIT)")])
def test_signal_leaves_no_truncated_output(tmp_path, sig, code, word):
    out = tmp_path / "trace.csv"
    out.write_text("t,pos_cmd\nold content\n")
    res = _run_and_signal(tmp_path, sig, out)
    assert res.returncode == code, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and word in lines[0], res.stderr
    assert "Traceback" not in res.stderr
    assert out.read_text() == "t,pos_cmd\nold content\n"  # --force replaces only a complete trace
    assert not list(tmp_path.glob(".*partial*"))
