"""A picture of one generated case: per trace the following error, the motor-to-table offset (semi-closed
loop) and the drive force, so a person can see what the withheld effect does before any diagnosis runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_case(case_dir: Path, traces: list[Path], title: str) -> Path:
    """Write ``case_dir/traces.png`` (one row per trace: following error [um], pos_fb - pos_meas [um] where
    recorded, force_drive [N]) and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(traces), 2, figsize=(13, 2.1 * len(traces)), squeeze=False)
    for row, path in zip(axes, traces, strict=True):
        d = np.genfromtxt(path, delimiter=",", names=True)
        t = d["t"]
        row[0].plot(t, (d["pos_cmd"] - d["pos_meas"]) * 1e6, lw=0.6, label="pos_cmd - pos_meas")
        if "pos_fb" in d.dtype.names:
            row[0].plot(t, (d["pos_fb"] - d["pos_meas"]) * 1e6, lw=0.6, label="pos_fb - pos_meas")
        row[0].set_ylabel("um")
        row[0].set_title(path.stem, fontsize=8, loc="left")
        row[1].plot(t, d["force_drive"], lw=0.5, label="force_drive")
        if "force_ext" in d.dtype.names:
            row[1].plot(t, d["force_ext"], lw=0.6, label="force_ext")
        row[1].set_ylabel("N")
        for ax in row:
            ax.tick_params(labelsize=7)
            ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t [s]")
    axes[-1, 1].set_xlabel("t [s]")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = Path(case_dir) / "traces.png"
    fig.savefig(out, dpi=70)
    plt.close(fig)
    return out
