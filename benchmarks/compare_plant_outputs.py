"""Bit-for-bit comparison of the plant's outputs between two source trees (e.g. a git worktree of an older commit
and this one): every output column (incl. the extras) of six configs x two profiles, compared with
``np.array_equal``. Used to show that new kernel options at their defaults change nothing.

    python benchmarks/compare_plant_outputs.py OTHER_TREE [THIS_TREE]

Each tree is simulated in its own process with ``PYTHONPATH=<tree>/src`` and its own configs/tests helpers.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

_SIMULATE = r'''
import sys, numpy as np
from pathlib import Path
root = Path(sys.argv[1])
sys.path.insert(0, str(root / "tests"))
from plant_helpers import config_with, rigid_force_axis
from virtualaxis.config import load_axis_config
from virtualaxis.sim import simulate_profile
cfgs = {
    "seed000": load_axis_config(root / "configs/seed000-hust.toml"),
    "seed000_dead_noise": config_with({"sensors": {"dead_time_s": 250e-6, "position_noise_m": 5e-8,
                                                   "current_noise_a": 0.005},
                                       "friction": {"coulomb_negative_n": 70.0, "viscous_n_s_per_m": 300.0}}),
    "seed004": load_axis_config(root / "configs/seed004-siemens.toml"),
    "gapbench": load_axis_config(root / "configs/examples/gap-bench-ballscrew.toml"),
    "rigid": load_axis_config(root / "configs/examples/rigid-force-axis.toml"),
    "rigid_dead": rigid_force_axis(coulomb_n=20.0, viscous_n_s_per_m=150.0).replace(sensors={"dead_time_s": 2e-3}),
}
out = {}
for name, cfg in cfgs.items():
    for spec in ("sine:stroke_mm=100,feed_mm_min=6000",
                 "ptp:distance_mm=50,feed_mm_min=10000,accel_m_s2=2,jerk_m_s3=50"):
        tr = simulate_profile(cfg, spec, 0.6, seed=3, extras=True, check=False)["x"]
        for k, v in tr.items():
            out[f"{name}|{spec[:3]}|{k}"] = v
np.savez(sys.argv[2], **out)
'''


def simulate(tree: Path, out: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    subprocess.run([sys.executable, "-c", _SIMULATE, str(tree), str(out)], env=env, check=True, cwd=tree)


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__)
        return 2
    other = Path(sys.argv[1]).resolve()
    this = Path(sys.argv[2]).resolve() if len(sys.argv) > 2 else ROOT
    with tempfile.TemporaryDirectory() as d:
        pa, pb = Path(d) / "a.npz", Path(d) / "b.npz"
        simulate(other, pa)
        simulate(this, pb)
        a, b = np.load(pa), np.load(pb)
        if set(a.files) != set(b.files):
            print("different column sets:", sorted(set(a.files) ^ set(b.files)))
            return 1
        bad = [k for k in a.files if not np.array_equal(a[k], b[k], equal_nan=True)]
    print(f"{len(a.files)} output arrays compared, {len(bad)} differ" + (f": {bad[:10]}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
