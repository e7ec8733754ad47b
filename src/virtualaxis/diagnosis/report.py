"""Writing the diagnosis: ``report.json``, ``report.html`` (plots embedded as base64 PNG) and
``calibrated.toml`` (the axis config with the accepted effects, via ``AxisConfig.to_toml``)."""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
import math
from pathlib import Path

import numpy as np

#: keys every report.json carries (checked by the tests)
REQUIRED_KEYS = ("baseline", "where", "effects", "hybrid", "conclusion")


def _clean(x):
    """JSON-safe: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if math.isfinite(v) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def report_json(report: dict) -> str:
    return json.dumps(_clean({k: v for k, v in report.items() if not k.startswith("_")}), indent=1)


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _plots(report: dict) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out: list[tuple[str, str]] = []
    pl = report.get("_plots")
    if not pl:
        return out
    tds, base_res, final_res, loc = pl["tds"], pl["base_res"], pl["final_res"], pl["loc"]
    chans = sorted({c for r in base_res for c in r})
    # residual over time, before and after, per channel (first fit and first held-out trace)
    show = [pl["fit_idx"][0]] + (pl["hold_idx"][:1] if pl["hold_idx"] else [])
    for i in show:
        td = tds[i]
        fig, axes = plt.subplots(len(chans), 1, figsize=(9, 1.9 * len(chans)), sharex=True, squeeze=False)
        for ax, ch in zip(axes[:, 0], chans, strict=True):
            if ch in base_res[i]:
                ax.plot(td.t, base_res[i][ch], lw=0.7, label="nominal model")
                ax.plot(td.t, final_res[i][ch], lw=0.7, label="calibrated model")
            ax.set_ylabel(f"{ch}\n[{_unit(ch)}]", fontsize=8)
            ax.grid(alpha=0.3)
        axes[0, 0].legend(fontsize=8, loc="upper right")
        axes[-1, 0].set_xlabel("t [s]")
        role = "fit" if i in pl["fit_idx"] else "held-out"
        fig.suptitle(f"residual measured - model: {td.name} ({role})", fontsize=10)
        out.append((f"Residual over time, {td.name}", _png(fig)))
    # where: shares per dimension for each channel
    dims = ("phase", "direction", "speed", "position", "time", "frequency")
    fig, axes = plt.subplots(len(chans), len(dims), figsize=(2.6 * len(dims), 2.2 * len(chans)), squeeze=False)
    for r, ch in enumerate(chans):
        for c, d in enumerate(dims):
            sh = loc.shares(ch, d)
            ax = axes[r, c]
            ax.bar(range(len(sh)), list(sh.values()), color="C0")
            tf = [e["time_fraction"] for e in loc.entries if e["channel"] == ch and e["dimension"] == d]
            if d != "frequency":
                ax.plot(range(len(sh)), tf, "k_", ms=14, label="share of samples")
            ax.set_xticks(range(len(sh)))
            ax.set_xticklabels(list(sh.keys()), rotation=60, fontsize=6, ha="right")
            ax.set_ylim(0, 1)
            if r == 0:
                ax.set_title(d, fontsize=9)
            if c == 0:
                ax.set_ylabel(ch, fontsize=8)
    fig.suptitle("share of the nominal residual energy per bin (bars) and share of samples (black)", fontsize=10)
    fig.tight_layout()
    out.append(("Where the gap lies", _png(fig)))
    # spectra
    fig, axes = plt.subplots(1, len(chans), figsize=(3.3 * len(chans), 2.6), squeeze=False)
    for ax, ch in zip(axes[0], chans, strict=True):
        sp = loc.spectra.get(ch)
        if sp:
            ax.loglog(np.asarray(sp["f_hz"])[1:], np.asarray(sp["psd"])[1:], lw=0.8)
        ax.set_title(ch, fontsize=9)
        ax.set_xlabel("f [Hz]")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("residual PSD")
    out.append(("Residual spectrum (nominal model)", _png(fig)))
    # effects ranking
    eff = report["effects"]
    if eff:
        fig, ax = plt.subplots(figsize=(7, 0.35 * len(eff) + 1))
        names = [e["name"] for e in eff][::-1]
        gains = [100 * e["heldout"]["gain"] for e in eff][::-1]
        colors = ["C2" if e["accepted"] else "C7" for e in eff][::-1]
        ax.barh(names, gains, color=colors)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_xlabel("held-out weighted residual energy reduction [%] (green: accepted)")
        out.append(("Candidate effects", _png(fig)))
    return out


def _unit(ch: str) -> str:
    from virtualaxis.diagnosis.trace import CHANNEL_UNITS

    return CHANNEL_UNITS.get(ch, "")


def _table(rows: list[list], head: list[str]) -> str:
    h = "".join(f"<th>{html.escape(str(x))}</th>" for x in head)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(x))}</td>" for x in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def _g(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.4g}"


def _change(x: float | None) -> str:
    return "new" if x is None else f"{100 * x:.1f} %"


def report_html(report: dict) -> str:
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>Gap diagnosis</title><style>"
        "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;margin:8px 0}"
        "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}img{max-width:100%}</style></head><body>",
        f"<h1>Sim-to-real gap diagnosis: {html.escape(report['axis'])}</h1>",
        f"<p>Config <code>{html.escape(report['config'])}</code>. Conclusion: <b>{html.escape(report['conclusion'])}"
        "</b></p>",
    ]
    if report["warnings"]:
        parts.append("<h2>Warnings</h2><ul>" + "".join(f"<li>{html.escape(w)}</li>" for w in report["warnings"])
                     + "</ul>")
    parts.append("<h2>Traces</h2>" + _table(
        [[t["name"], t["role"], t["samples"], ", ".join(t["channels"])] for t in report["traces"]],
        ["trace", "role", "samples", "channels"]))
    parts.append("<h2>Baseline gap (nominal model)</h2>" + _table(
        [[ch, m["unit"], _g(m["rmse"]), _g(m["mae"]), _g(m["max"])] for ch, m in report["baseline"].items()],
        ["channel", "unit", "RMSE", "mean |e|", "max |e|"]))
    cc = report.get("controller_check") or []
    if cc:
        def gains(g: dict) -> str:
            ti = f"Ti {_g(g['ti_s'])} s" if g["ti_s"] > 0 else "P speed loop"
            return f"Kv {_g(g['kv_per_s'])} 1/s, Kp {_g(g['kp'])}, {ti}, vel. ff {_g(g['velocity_ff'])}"

        parts.append("<h2>Controller check</h2><p>The control law (config or sidecar) replayed on each trace's "
                     "measured signals: share of the controller output's variance it leaves unexplained, and a law "
                     "identified from the trace. Identified gains are used for a trace only where the configured "
                     "law clearly does not fit (see docs/diagnosis.md).</p>" + _table(
                         [[c["trace"], c["channel"], _g(c["unexplained_config"]), _g(c["unexplained_identified"]),
                           gains(c["config_gains"]), gains(c["identified_gains"]), c["used"], c["note"]]
                          for c in cc],
                         ["trace", "output", "unexplained (config)", "unexplained (identified)", "config",
                          "identified", "used", "note"]))
    cw = report.get("channel_weights") or {}
    if cw:
        parts.append("<h2>Channel weights</h2><p>Every cost divides a channel's residual by its sigma: the largest "
                     "of its noise floor, a tenth of its baseline gap, its quantisation (grid step / &radic;12) and "
                     "the model's own chaos (how much the prediction changes under a 1e-12 m change of the "
                     "command).</p>" + _table(
                         [[ch, _g(v["sigma"]), _g(v["quantum"]), _g(v["chaos"]), _g(v["n_eff_fraction"])]
                          for ch, v in cw.items()], ["channel", "sigma", "grid step", "chaos", "n_eff / n"]))
    rows = []
    for ch, lst in report["where_summary"].items():
        for e in lst:
            rows.append([ch, e["dimension"], e["bin"], f"{100 * e['share']:.1f} %", f"{e['concentration']:.2f}"])
    parts.append("<h2>Where the gap concentrates</h2>" + _table(
        rows, ["channel", "dimension", "bin", "share of residual energy", "share / share of samples"]))
    rows = []
    for e in report["effects"]:
        ps = "; ".join(f"{k} = {_g(v['value'])} {v['unit']} " + (f"± {_g(v['stderr'])}" if v.get("determined", True)
                                                                  else "(not determined by the fit traces)")
                       for k, v in e["params"].items())
        rows.append([e["rank"], e["name"], "yes" if e["accepted"] else "no", f"{100 * e['heldout']['gain']:.1f} %",
                     _g(e["ic_delta"]), _g(e["signature_overlap"]), _change(e.get("relative_change")), ps])
    parts.append("<h2>Candidate effects</h2>" + _table(
        rows, ["rank", "effect", "accepted", "held-out reduction", "ΔBIC", "signature overlap", "change vs model",
               "parameters"]))
    jr = report.get("joint_refit")
    if jr:
        rows = [[e, "; ".join(f"{k} = {_g(v)}" for k, v in jr["sequential_values"][e].items()),
                 "; ".join(f"{k} = {_g(v)}" for k, v in jr["joint_values"].get(e, {}).items())] for e in jr["effects"]]
        verdict = ("kept (lower fit cost, held-out cost not higher)" if jr["accepted"]
                   else "not kept (it did not lower the fit cost without raising the held-out cost)")
        parts.append(f"<h2>Joint refit of the accepted effects: {verdict}</h2>"
                     f"<p>weighted cost fit {_g(jr['fit_cost_sequential'])} → {_g(jr['fit_cost_joint'])}, held out "
                     f"{_g(jr['heldout_cost_sequential'])} → {_g(jr['heldout_cost_joint'])}</p>"
                     + _table(rows, ["effect", "forward selection", "joint refit"]))
    if report["cumulative"]:
        rows = []
        for c in report["cumulative"]:
            for ch in c["fit_after"]:
                hb = c["heldout_before"].get(ch, {})
                ha = c["heldout_after"].get(ch, {})
                rows.append([c["after"], ch, _g(c["fit_before"][ch]["rmse"]), _g(c["fit_after"][ch]["rmse"]),
                             _g(hb.get("rmse")), _g(ha.get("rmse")), _g(ha.get("mae")), _g(ha.get("max"))])
        parts.append("<h2>How far the gap shrinks (cumulative)</h2>" + _table(
            rows, ["after adding", "channel", "fit RMSE before", "fit RMSE after", "held-out RMSE before",
                   "held-out RMSE after", "held-out mean |e|", "held-out max |e|"]))
    if report.get("contour"):
        rows = []
        for c in report["contour"]:
            for label, m in c["models"].items():
                rows.append([" / ".join(c["traces"]), label, _g(c["measured_max_m"]), _g(m["predicted_max_m"]),
                             _g(m["prediction_error_max_m"]), _g(m["prediction_error_rms_m"])])
        parts.append("<h2>Contour error of two-axis moves (seed 000 Table 4) [m]</h2>" + _table(
            rows, ["X / Y traces", "model", "measured max", "predicted max", "prediction error max",
                   "prediction error RMS"]))
    hyb = report.get("hybrid")
    if hyb:
        rows = []
        for m in hyb["models"]:
            for ch, v in m["channels"].items():
                worse = m.get("verdict", {}).get("channels", {}).get(ch, {}).get("worse", False)
                rows.append([m["model"], ch, _g(v["heldout_rmse_before"]), _g(v["heldout_rmse_after"]),
                             _g(v["ratio"]), "worse beyond its noise" if worse else ""])
        parts.append(f"<h2>Data-driven residual model on top of the calibrated physics (judged on {hyb['judged_on']})"
                     "</h2>" + _table(
                         rows, ["model", "channel", "RMSE physics only", "RMSE hybrid", "before / after", "verdict"])
                     + f"<p>best: {html.escape(str(hyb.get('model')))}; improves (no channel worse beyond its noise): "
                     f"{hyb.get('improves')}</p>")
    for title, b64 in _plots(report):
        parts.append(f"<h2>{html.escape(title)}</h2><img src='data:image/png;base64,{b64}'>")
    parts.append("<h2>Timing</h2>" + _table([[k, _g(v)] for k, v in report["timing"].items()], ["step", "value"]))
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(report: dict, out_dir: Path) -> dict[str, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "report.json", "html": out_dir / "report.html", "toml": out_dir / "calibrated.toml"}
    paths["json"].write_text(report_json(report), encoding="utf-8")
    paths["html"].write_text(report_html(report), encoding="utf-8")
    cfg = report.get("_calibrated_cfg")
    if cfg is not None:
        srcs = dict(cfg.sources)
        base = report.get("_base_cfg")
        if base is not None:
            a, b = base.to_dict(), cfg.to_dict()
            for sec, vals in b.items():
                if not isinstance(vals, dict):
                    continue
                for k, v in vals.items():
                    if a.get(sec, {}).get(k) != v and sec == "control":
                        srcs[f"{sec}.{k}"] = ("gap diagnosis: controller identified from the traces (median over "
                                              "traces, report.json controller_check)")
                    elif a.get(sec, {}).get(k) != v:
                        srcs[f"{sec}.{k}"] = (f"gap diagnosis ({report['conclusion']}) fitted on "
                                              f"{', '.join(_fit_names(report))}")
        cfg = dataclasses.replace(cfg, sources=srcs)
        header = (f"calibrated by virtualaxis diagnose from {report['config']}\n"
                  f"accepted effects: {report['conclusion']}")
        paths["toml"].write_text(cfg.to_toml(header), encoding="utf-8")
    return paths


def _fit_names(report: dict) -> list[str]:
    return [t["name"] for t in report["traces"] if t["role"] == "fit"]
