"""`virtualaxis demo` (the README's main-job command) runs by itself and writes its plot and summary."""

from __future__ import annotations

import json
import subprocess
import sys


def test_demo_runs_and_the_drive_matches_the_offline_simulation(tmp_path):
    out = tmp_path / "demo"
    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    r = subprocess.run(
        [*cli, "demo", "--out", str(out), "--stroke-mm", "20", "--no-pace"], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "demo_summary.json").read_text())
    assert (out / "demo_csp_move.png").stat().st_size > 10_000
    assert summary["offline_match"]["cycles_differing"] == 0
    assert summary["max_abs_following_error_um"] > 100  # a real lag, v / Kv
    assert summary["final_statusword"] in ("0x0231", "0x0631")  # ready to switch on after the move
    assert summary["runtime"]["overruns"] == 0
    assert "following error" in r.stdout


def test_demo_rejects_a_stroke_beyond_the_travel(tmp_path):
    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    r = subprocess.run(
        [*cli, "demo", "--out", str(tmp_path), "--stroke-mm", "5000"], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 2 and r.stderr.startswith("error: --stroke-mm")
