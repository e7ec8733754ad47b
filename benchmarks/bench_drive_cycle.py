"""Cost of one drive cycle (CiA 402 logic + plant step) per mode of operation, in process, no bus.

    python benchmarks/bench_drive_cycle.py [CONFIG.toml]

Prints CPU microseconds (this thread) per 1 ms drive cycle (best of 5 blocks of 2000 cycles) in PV, PP, CST. For an A/B
against another checkout run it once per checkout, interleaved, e.g.
``PYTHONPATH=OTHER/src python benchmarks/bench_drive_cycle.py`` (a ``git worktree`` of the baseline commit).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from virtualaxis.config import load_axis_config
from virtualaxis.drive.core import Drive

# the default config comes from this checkout, so a baseline without virtualaxis.resources runs too
# mode -> objects written after enabling: PV 50 mm/s, PP a 40 mm move, CST 2 % rated torque
CASES = {"PV": (3, {0x60FF: 50_000}), "PP": (1, {0x607A: 40_000}), "CST": (10, {0x6071: 20})}


def cycle_us(cfg, mode: int, writes: dict[int, int], blocks: int = 5, n: int = 2000) -> float:
    drive = Drive(cfg, seed=1)
    drive.write_object(0x6060, 0, mode)
    for cw in (0x06, 0x07, 0x0F):
        drive.write_object(0x6040, 0, cw)
    for index, value in writes.items():
        drive.write_object(index, 0, value)
    if mode == 1:
        drive.write_object(0x6040, 0, 0x1F)  # new set-point
    drive.step(200)
    best = float("inf")
    for _ in range(blocks):
        t0 = time.thread_time()  # this thread's CPU time: what a loaded machine disturbs least
        drive.step(n)
        best = min(best, (time.thread_time() - t0) / n)
    return best * 1e6


def main() -> None:
    default = Path(__file__).resolve().parents[1] / "configs" / "seed000-hust.toml"
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else default
    cfg = load_axis_config(path)
    import virtualaxis

    figures = {name: cycle_us(cfg, mode, writes) for name, (mode, writes) in CASES.items()}
    print(f"{Path(virtualaxis.__file__).parents[2]}: "
          + "  ".join(f"{k} {v:.2f} us/cycle" for k, v in figures.items()))


if __name__ == "__main__":
    main()
