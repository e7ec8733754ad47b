"""Writing the diagnosis: ``report.json``, ``report.html`` (plots embedded as base64 PNG) and
``calibrated.toml`` (the axis config with the accepted effects, via ``AxisConfig.to_toml``)."""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only
    from virtualaxis.config import AxisConfig
    from virtualaxis.diagnosis.data import TraceData
    from virtualaxis.diagnosis.where import Localisation

#: keys every report.json carries (checked by the tests)
REQUIRED_KEYS = ("baseline", "where", "effects", "hybrid", "conclusion")


@dataclass(frozen=True)
class Plots:
    """The arrays the report's plots are drawn from."""

    tds: list[TraceData]
    base_res: list[dict[str, np.ndarray]]
    final_res: list[dict[str, np.ndarray]]
    loc: Localisation
    fit_idx: list[int]
    hold_idx: list[int]


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


def _plots(report: dict, pl: Plots | None) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out: list[tuple[str, str]] = []
    if pl is None:
        return out
    tds, base_res, final_res, loc = pl.tds, pl.base_res, pl.final_res, pl.loc
    chans = sorted({c for r in base_res for c in r})
    # residual over time, before and after, per channel (first fit and first held-out trace)
    show = [pl.fit_idx[0]] + (pl.hold_idx[:1] if pl.hold_idx else [])
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
        role = "fit" if i in pl.fit_idx else "held-out"
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
    eff = [e for e in report["effects"] if e.get("fitted", True)]
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


#: (prefix, factor) for showing a value of a base unit in engineering notation
_PREFIXES = ((1e-9, "n"), (1e-6, "u"), (1e-3, "m"), (1.0, ""), (1e3, "k"), (1e6, "M"), (1e9, "G"))


_SI = ("m", "N", "s", "Hz", "A", "V", "rad")


def _scale(ref: float, unit: str) -> tuple[float, str]:
    """(factor, unit with prefix) to show values of magnitude ``ref``; (1, unit) for compound units."""
    if unit in _SI and ref > 0 and math.isfinite(ref):
        factor, prefix = next(((f, p) for f, p in reversed(_PREFIXES) if ref >= f), _PREFIXES[0])
        return factor, prefix + unit
    return 1.0, unit


def _eng_pair(before: float | None, after: float | None, unit: str, stderr: float | None = None) -> str:
    """``17 -> 50.1 +- 0.15 um`` (``before`` None: ``50.1 +- 0.15 um``), all in the prefix of the larger value."""
    vals = [abs(v) for v in (before, after) if v is not None and math.isfinite(v)]
    factor, u = _scale(max(vals) if vals else 0.0, "" if unit in ("1", "-") else unit)

    def num(v: float | None) -> str:
        return "-" if v is None or not math.isfinite(v) else f"{v / factor:.3g}"

    txt = f"{num(before)} -> {num(after)}" if before is not None else num(after)
    if stderr is not None and math.isfinite(stderr):
        txt += f" +- {stderr / factor:.2g}"
    return f"{txt} {u}".rstrip()


_POSITION_CHANNELS = ("pos_meas", "pos_fb", "motor_pos")


def _error_change(side: dict) -> str:
    """``held-out position error -97 %`` from an effect's before/after RMSE per channel: the position channel
    when there is one, else every channel."""
    before, after = side.get("rmse_before") or {}, side.get("rmse_after") or {}
    chans = [c for c in _POSITION_CHANNELS if c in before and c in after and before[c]]
    if chans:
        c = chans[0]
        return f"position error {100 * (after[c] / before[c] - 1):+.0f} %"
    parts = [f"{c} {100 * (after[c] / before[c] - 1):+.0f} %" for c in before if c in after and before[c]]
    return "error " + ", ".join(parts) if parts else ""


def headline(report: dict) -> list[str]:
    """What was found, in engineering units, one line per accepted effect: the config's value -> the fitted one
    +- its standard error (``backlash: gap_m 17 -> 50.1 +- 0.15 um; held-out position error -97 %``); a
    parameter the config does not have (a scale, an added amount) shows the fitted value alone."""
    held = bool(report.get("baseline_heldout"))
    changes = report.get("calibrated_changes") or {}
    out = []
    for e in report["effects"]:
        if not e.get("accepted"):
            continue
        ps = []
        for k, v in e["params"].items():
            was = next((c["from"] for key, c in changes.items() if key.rsplit(".", 1)[-1] == k
                        and isinstance(c.get("from"), (int, float)) and not isinstance(c.get("from"), bool)), None)
            determined = v.get("determined", True) and v.get("stderr") is not None
            txt = _eng_pair(was, v.get("value"), v.get("unit", ""), v["stderr"] if determined else None)
            if not v.get("determined", True):
                txt += " (not determined by the fit traces)"
            ps.append(f"{k} {txt}")
        change = _error_change(e["heldout"] if held else e["fit"])
        out.append(f"{e['name']}: {', '.join(ps)}" + (f"; {'held-out' if held else 'fit'} {change}" if change
                                                      else ""))
    if not out:
        out.append(report["conclusion"])
    return out


def verdict_text(verdict: dict) -> str:
    """Per channel RMSE before -> after in engineering units (``pos_meas 148 -> 0.93 um``)."""
    from virtualaxis.diagnosis.trace import CHANNEL_UNITS

    parts = []
    for ch, v in (verdict or {}).get("channels", {}).items():
        worse = " (worse beyond its noise)" if v.get("worse") else ""
        parts.append(f"{ch} {_eng_pair(v.get('before'), v.get('after'), CHANNEL_UNITS.get(ch, ''))}{worse}")
    return ", ".join(parts)


def mark_unfitted(report: dict) -> None:
    """Candidates that were only screened (never refined) or failed carry no fitted values: their parameters,
    held-out figures and change vs the model are removed, ``fitted`` is False and ``not_fitted`` says why."""
    for e in report.get("effects", []):
        fitted = e.get("stage") != "screen" and not e.get("error")
        e["fitted"] = fitted
        if fitted:
            continue
        e["not_fitted"] = (f"fit failed: {e['error']}" if e.get("error") else
                           f"screened only: explained {100 * (e.get('screen_gain') or 0.0):.2g} % of the fit "
                           "residual at its screening start, below the share that is refined")
        e["params"] = {}
        e["params_at_bound"] = []
        e["relative_change"] = None
        e["ic_delta"] = None
        e["verdict"] = None
        for side in ("fit", "heldout"):
            if isinstance(e.get(side), dict):
                e[side] = {"rmse_before": e[side].get("rmse_before", {}), "rmse_after": {}, "metrics_after": {},
                           "gain": None, "gain_per_channel": {}}


def _change(x: float | None) -> str:
    return "new" if x is None else f"{100 * x:.1f} %"


def report_html(report: dict, plots: Plots | None = None) -> str:
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>Gap diagnosis</title><style>"
        "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse;margin:8px 0}"
        "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}img{max-width:100%}</style></head><body>",
        f"<h1>Sim-to-real gap diagnosis: {html.escape(report['axis'])}</h1>",
        f"<p>Config <code>{html.escape(report['config'])}</code>. Conclusion: <b>{html.escape(report['conclusion'])}"
        "</b></p>",
        "<ul>" + "".join(f"<li>{html.escape(h)}</li>" for h in report.get("headline", [])) + "</ul>",
    ]
    if report.get("calibrated_diff"):
        parts.append("<h2>calibrated.toml: changed lines</h2><pre>"
                     + html.escape("\n".join(report["calibrated_diff"])) + "</pre>")
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
        if not e.get("fitted", True):
            rows.append([e["rank"], e["name"], "no", "-", "-", "-", "-", e.get("not_fitted", "not fitted")])
            continue
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
    for title, b64 in _plots(report, plots):
        parts.append(f"<h2>{html.escape(title)}</h2><img src='data:image/png;base64,{b64}'>")
    parts.append("<h2>Timing</h2>" + _table([[k, _g(v)] for k, v in report["timing"].items()], ["step", "value"]))
    parts.append("</body></html>")
    return "\n".join(parts)


def _calibrated_text(report: dict, cfg: AxisConfig | None, base: AxisConfig | None) -> str | None:
    """The calibrated config as text: the input file with only the changed values edited on their lines
    (:mod:`virtualaxis.diagnosis.calibrated`), checked by loading it again; when the input cannot be read or the
    edit does not load to the same values, the whole config written anew (``AxisConfig.to_toml``)."""
    if cfg is None:
        return None
    srcs = dict(cfg.sources)
    changes: dict[str, object] = {}
    new_sources: dict[str, str] = {}
    if base is not None:
        a, b = base.to_dict(), cfg.to_dict()
        for sec, vals in b.items():
            if not isinstance(vals, dict):
                continue
            for k, v in vals.items():
                if a.get(sec, {}).get(k) == v or isinstance(v, dict):
                    continue
                changes[f"{sec}.{k}"] = v
                if sec == "control":
                    new_sources[f"{sec}.{k}"] = ("gap diagnosis: controller identified from the traces (median over "
                                                 "traces, report.json controller_check)")
                else:
                    new_sources[f"{sec}.{k}"] = (f"gap diagnosis ({report['conclusion']}) fitted on "
                                                 f"{', '.join(_fit_names(report))}")
    srcs.update(new_sources)
    header = (f"calibrated by virtualaxis diagnose from {report['config']}\n"
              f"accepted effects: {report['conclusion']}")
    rewritten = dataclasses.replace(cfg, sources=srcs).to_toml(header)
    path = getattr(base, "path", None)
    try:
        original = Path(path).read_text(encoding="utf-8") if path else None
    except (OSError, UnicodeDecodeError):
        original = None
    report["calibrated_changes"] = {k: {"from": _plain(base.to_dict(), k) if base is not None else None,
                                        "to": v} for k, v in changes.items()}
    if original is None:
        report["calibrated_diff"] = []
        return rewritten
    from virtualaxis.diagnosis.calibrated import edit_config_text, text_diff

    edited = edit_config_text(original, changes, new_sources)
    if not _loads_to(edited, Path(path), cfg):
        report.setdefault("warnings", []).append(
            "calibrated.toml: the input config could not be edited in place (a value did not load back as "
            "fitted); it is written anew with every key")
        report["calibrated_diff"] = text_diff(original, rewritten, str(path), "calibrated.toml")
        return rewritten
    report["calibrated_diff"] = text_diff(original, edited, str(path), "calibrated.toml")
    return edited


def _plain(d: dict, key: str):
    sec, k = key.rsplit(".", 1)
    return d.get(sec, {}).get(k)


def _loads_to(text: str, original_path: Path, cfg) -> bool:
    """``text`` loads with the config loader (next to the input, so relative references resolve alike) to
    ``cfg``'s values."""
    import os
    import tempfile

    from virtualaxis.config import load_axis_config
    from virtualaxis.config.errors import ConfigError

    fd, tmp = tempfile.mkstemp(suffix=".toml", prefix=".calibrated-", dir=str(original_path.parent)
                               if os.access(original_path.parent, os.W_OK) else None)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        loaded = load_axis_config(tmp).to_dict()
    except (ConfigError, OSError, ValueError):
        return False
    finally:
        Path(tmp).unlink(missing_ok=True)
    want = cfg.to_dict()
    return all(loaded.get(sec) == vals for sec, vals in want.items() if isinstance(vals, dict))


def write_report(report: dict, out_dir: Path, *, calibrated: AxisConfig | None = None,
                 nominal: AxisConfig | None = None, plots: Plots | None = None) -> dict[str, Path]:
    """``report.json``, ``report.html`` (with ``plots``) and ``calibrated.toml`` (``calibrated``, edited from
    ``nominal``'s file) into ``out_dir``; the report gets its headline and calibrated changes."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "report.json", "html": out_dir / "report.html", "toml": out_dir / "calibrated.toml"}
    mark_unfitted(report)
    toml_text = _calibrated_text(report, calibrated, nominal)
    report["headline"] = headline(report)
    paths["json"].write_text(report_json(report), encoding="utf-8")
    paths["html"].write_text(report_html(report, plots), encoding="utf-8")
    if toml_text is not None:
        paths["toml"].write_text(toml_text, encoding="utf-8")
    return paths


def _fit_names(report: dict) -> list[str]:
    return [t["name"] for t in report["traces"] if t["role"] == "fit"]
