"""Matplotlib figures (Agg backend) for the CLI commands and studies."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_bode(frfs: dict, path: Path, title: str = "") -> None:
    keys = ["mechanics_speed", "speed_closed_loop", "position_closed_loop", "position_open_loop"]
    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for k in keys:
        fr = frfs[k]
        mag = fr.magnitude_db
        if k == "mechanics_speed":
            mag = mag - mag[0]
            label = fr.name + " (normalised)"
        else:
            label = fr.name
        axes[0].semilogx(fr.freq_hz, mag, label=label)
        axes[1].semilogx(fr.freq_hz, fr.phase_deg, label=label)
    axes[0].set_ylabel("magnitude [dB]")
    axes[1].set_ylabel("phase [deg]")
    axes[1].set_xlabel("frequency [Hz]")
    axes[0].legend(fontsize=7)
    axes[0].grid(True, which="both", alpha=0.3)
    axes[1].grid(True, which="both", alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_modal(cfg, results: list[dict], folder: Path) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4))
    for i in range(min(4, min(len(r["natural_frequencies_hz"]) for r in results) if results else 0)):
        ax.plot([r["nut_position_m"] for r in results], [r["natural_frequencies_hz"][i] for r in results], "o-",
                label=f"mode {i + 1}")
    ax.set_xlabel("nut position from fixed bearing [m]")
    ax.set_ylabel("natural frequency [Hz]")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(folder / "frequencies_vs_position.png", dpi=110)
    plt.close(fig)
    r = results[len(results) // 2]
    n_modes = min(4, len(r["mode_shapes"]))
    if n_modes:
        fig, axes = plt.subplots(1, n_modes, figsize=(3 * n_modes, 3.5), sharey=True)
        axes = axes if n_modes > 1 else [axes]
        for i in range(n_modes):
            axes[i].bar(range(len(r["body_names"])), r["mode_shapes"][i])
            axes[i].set_xticks(range(len(r["body_names"])), r["body_names"], rotation=60, fontsize=7)
            axes[i].set_title(f"{r['natural_frequencies_hz'][i]:.0f} Hz")
        fig.suptitle("mode shapes (rotations x lead/2pi)")
        fig.tight_layout()
        fig.savefig(folder / "mode_shapes.png", dpi=110)
        plt.close(fig)


def plot_xy(path: Path, x, ys: dict, xlabel: str, ylabel: str, title: str = "", paper: dict | None = None) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, y in ys.items():
        ax.plot(x, y, "o-", label=label)
    if paper:
        for label, (px, py) in paper.items():
            ax.plot(px, py, "s--", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_kv_weight_sensitivity(path: Path, sens: dict, title: str = "") -> None:
    """Seed 004 cost-function weights: optimum k_v over the weight simplex (w_precision, w_energy; w_time = rest),
    one panel per reading of "precision"; the paper's optimum +-tolerance is outlined."""
    import numpy as np

    names = list(sens["readings"])
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 4.6), squeeze=False)
    g = sens["grid"]
    x = np.array([r["w_precision"] for r in g])
    y = np.array([r["w_energy"] for r in g])
    lo = sens["paper_kv_per_min"] * (1 - sens["tolerance"])
    hi = sens["paper_kv_per_min"] * (1 + sens["tolerance"])
    for ax, name in zip(axes[0], names, strict=True):
        z = np.array([r[f"optimum_kv_per_min_{name}"] for r in g])
        sc = ax.scatter(x, y, c=z, cmap="viridis", s=55, marker="s")
        hit = (z >= lo) & (z <= hi)
        ax.scatter(x[hit], y[hit], facecolors="none", edgecolors="red", s=90, linewidths=1.2,
                   label=f"within {100 * sens['tolerance']:.0f} % of {sens['paper_kv_per_min']:g} 1/min")
        ax.plot([1 / 3], [1 / 3], "w*", ms=14, mec="k", label="equal weights")
        ax.set_xlabel("weight of precision w_e")
        ax.set_ylabel("weight of energy w_E (w_tau = 1 - w_e - w_E)")
        ax.set_title(f"precision = {name.replace('_', ' ')}", fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
        fig.colorbar(sc, ax=ax, label="optimum kv [1/min]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
