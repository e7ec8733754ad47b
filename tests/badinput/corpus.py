"""The bad-input corpus (docs/bad-input.md): ~460 bad inputs built from
classes (every value class on a spread of config keys, misspelt keys, wrong TOML types, missing sections, every
numeric CLI option with empty / nan / subnormal / huge values, list options, profile specs, move files, traces
and sidecars, output paths, serve / conformance / fault against a bus where nothing answers), each run in a
forked child of one process that has imported the CLI and loaded the compiled kernels (a real process with its
own exit status, stderr and a time limit: 30 s, 150 s for diagnose / study / rcsa / identify-joints).

Each result is classified: clear (exit 2, ONE line ``error: ...``), misleading (other status or more lines),
traceback (an internal error), hang (over the limit), accepted (exit 0: checked by hand: right or silently
wrong); ``+leftover`` when a refused case left a file or folder behind (or changed an input).

    python3 tests/badinput/corpus.py [REGEX]       # A18_JOBS=3, A18_OUT=/tmp/badinput-corpus.json (+ .log per case)

Not part of the test suite (about 15 minutes on 2 vCPUs); tests/test_badinput_cli.py keeps one case per defect
class it found.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(os.environ.get("VA_ROOT", Path(__file__).resolve().parents[2]))
C4 = ROOT / "configs" / "seed004-siemens.toml"
RCSA = ROOT / "configs" / "seed002-usst.toml"
GOOD = ROOT / "tests" / "badinput" / "traces" / "good.csv"
C4TXT = C4.read_text()
CASES: list[tuple[str, list[str], dict]] = []


def case(cid, argv, expect="err", files=None, check=None):
    CASES.append((cid, argv, {"expect": expect, "files": files or {}, "check": check}))


def set_key(text, section, key, value):
    """Replace (or add) `key = ...` in [section]."""
    lines = text.splitlines()
    out, cur, done = [], None, False
    for ln in lines:
        m = re.match(r"\s*\[([^\]]+)\]\s*$", ln)
        if m:
            if cur == section and not done:
                out.append(f"{key} = {value}")
                done = True
            cur = m.group(1).strip()
        if cur == section and re.match(rf"\s*{re.escape(key)}\s*=", ln):
            out.append(f"{key} = {value}")
            done = True
            continue
        out.append(ln)
    if not done:
        if cur != section:
            out.append(f"[{section}]")
        out.append(f"{key} = {value}")
    return "\n".join(out) + "\n"


def drop_section(text, section):
    out, cur = [], None
    for ln in text.splitlines():
        m = re.match(r"\s*\[([^\]]+)\]\s*$", ln)
        if m:
            cur = m.group(1).strip()
        if cur == section:
            continue
        out.append(ln)
    return "\n".join(out) + "\n"


# ---------------- config: every value class on a spread of numeric keys ---------------------------------------
KEYS = [
    ("mechanics", "lead_m"),
    ("mechanics", "table_mass_kg"),
    ("motor", "pole_pairs"),
    ("control", "kv_per_min"),
    ("friction", "coulomb_n"),
    ("limits", "max_velocity_m_s"),
    ("sensors", "linear_scale_resolution_m"),
    ("control", "velocity_ff_factor"),
    ("axis", "stroke_m"),
    ("simulation", "seed"),
    ("sensors", "motor_encoder_counts_per_rev"),
    ("control", "position_cycle_s"),
]
VALUES = {
    "neg": "-1",
    "zero": "0",
    "1e308": "1e308",
    "negzero": "-0.0",
    "str": '"abc"',
    "bool": "true",
    "array": "[1, 2]",
    "table": "{ a = 1 }",
    "int2p63": str(2**63),
    "intm2p63": str(-(2**63) - 1),
    "value-str": '{ value = "1" }',
    "value-missing": '{ source = "x" }',
    "tiny": "1e-320",
}
for sec, key in KEYS:
    for vn, v in VALUES.items():
        txt = set_key(C4TXT, sec, key, v)
        case(f"cfg-{sec}.{key}={vn}", ["modal", "--config", "{T}/c.toml"], "any", {"c.toml": txt})
# misspelled keys at every level, wrong types at section level, missing sections
for sec, key in [
    ("mechanics", "lead_mm"),
    ("axis", "strok_m"),
    ("control", "kv_per_minute"),
    ("limits", "travel_maxm"),
    ("simulation", "sed"),
]:
    case(
        f"cfg-misspelled-{sec}.{key}",
        ["modal", "--config", "{T}/c.toml"],
        "err",
        {"c.toml": set_key(C4TXT, sec, key, "1.0")},
    )
case("cfg-unknown-top-key", ["modal", "--config", "{T}/c.toml"], "err", {"c.toml": "version = 3\n" + C4TXT})
case(
    "cfg-unknown-in-value-table",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": set_key(C4TXT, "mechanics", "lead_m", '{ value = 0.01, sourse = "x" }')},
)
case(
    "cfg-section-is-number",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": "motor = 5\n" + drop_section(C4TXT, "motor")},
)
case(
    "cfg-section-array-of-tables",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": C4TXT.replace("[limits]", "[[limits]]")},
)
case(
    "cfg-section-is-string",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": 'friction = "on"\n' + drop_section(C4TXT, "friction")},
)
for sec in ("mechanics", "motor", "control", "limits", "axis", "sensors", "inverter"):
    case(f"cfg-missing-section-{sec}", ["modal", "--config", "{T}/c.toml"], "any", {"c.toml": drop_section(C4TXT, sec)})
for sec, key, v in [
    ("friction", "enabled", '"yes"'),
    ("friction", "enabled", "1"),
    ("mechanics", "model", '"bogus"'),
    ("mechanics", "screw_mounting", "5"),
    ("control", "position_feedback", '"nonsense"'),
    ("axis", "name", "5"),
    ("axis", "name", '""'),
    ("mechanics", "lead_m", "{ value = 0.01, source = 5 }"),
    ("actuator", "kind", '"stepper"'),
    ("inverter", "model", "[1]"),
    ("backlash", "enabled", '"false"'),
]:
    case(f"cfg-{sec}.{key}={v}", ["modal", "--config", "{T}/c.toml"], "err", {"c.toml": set_key(C4TXT, sec, key, v)})
case(
    "cfg-travel-min-1e308",
    ["modal", "--config", "{T}/c.toml"],
    "any",
    {"c.toml": set_key(C4TXT, "limits", "travel_min_m", "-1e308")},
)
case(
    "cfg-dotted-key-into-value",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": C4TXT + "\n[mechanics.lead_m]\nextra = 1\n"},
)

case(
    "cfg-int-400-digits",
    ["modal", "--config", "{T}/c.toml"],
    "err",
    {"c.toml": set_key(C4TXT, "effects", "force_offset_n", "9" * 400)},
)
case("cfg-metadata-nan", ["modal", "--config", "{T}/c.toml"], "err", {"c.toml": C4TXT + "\n[metadata]\nw = nan\n"})
case("cfg-drive-inf", ["modal", "--config", "{T}/c.toml"], "err", {"c.toml": C4TXT + "\n[drive]\nx = inf\n"})

# ---------------- CLI numeric options -----------------------------------------------------------------------
SIM = ["simulate", "--config", str(C4), "--profile", "step:distance_um=10", "--out", "{T}/t.csv"]
for v in ["", "1e-320", "-0", "1e308", " ", "0x10", "1_0"]:
    case(f"sim-duration={v!r}", SIM + ["--duration", v], "any")
for v in ["", "1.5", "1e3", "-0"]:
    case(f"sim-seed={v!r}", SIM + ["--seed", v], "any")
for v in ["-1", "0", "inf", "1e-320", ""]:
    case(f"sim-max-output-mb={v!r}", SIM + ["--max-output-mb", v], "any")
MOD = ["modal", "--config", str(C4)]
for v in ["0.8,,1.0", "0.5,0.5", "0.9,0.1", "-0.1", "", ",", "1e-320", "0.5;0.6", "50%", " 0.5 , 0.6 "]:
    case(f"modal-positions={v!r}", MOD + ["--positions", v], "any")
FRF = ["frf", "--config", str(C4), "--out", "{T}/o"]
for opt, vals in [
    ("--position", ["-1", "2", "1e-320", "", "-0"]),
    ("--fmin", ["0", "1e-320", "", "-inf"]),
    ("--points", ["-1", "", "1e20", "2", "1.5"]),
    ("--fmax", ["0", "-1", "1e-320"]),
]:
    for v in vals:
        case(f"frf{opt}={v!r}", FRF + [opt, v], "any")
case("frf-fmin-eq-fmax", FRF + ["--fmin", "100", "--fmax", "100"], "err")
for study in ["kv-sweep", "support-stiffness", "feed-sweep"]:
    for v in ["", "1,,2", "0", "1e308", "nan", "5,5"]:
        case(
            f"study-{study}-values={v!r}", ["study", study, "--config", str(C4), "--out", "{T}/s", "--values", v], "any"
        )
case(
    "study-inverter-values-ignored",
    ["study", "inverter", "--config", str(C4), "--out", "{T}/s", "--values", "1,2"],
    "any",
)
RC = ["rcsa", "--config", str(RCSA)]
for v in ["-1", "1e308", "0", "", "0.5,,0.6", "0.6,0.6", "100"]:
    case(f"rcsa-positions={v!r}", RC + ["--positions", v], "any")
case("rcsa-config-without-rcsa", ["rcsa", "--config", str(C4)], "err")
ID = ["identify-joints", "--config", str(RCSA), "--modes", "{T}/m.csv"]
MODES = "position_m,order,freq_hz\n0.6,1,30\n0.8,1,31\n"
for v in ["", "0.6,0.6", "-1", "100", "0.6,,0.8"]:
    case(f"ident-train={v!r}", ID + ["--train-positions", v], "any", {"m.csv": MODES})
for opt, v in [
    ("--population", "0"),
    ("--population", "-1"),
    ("--workers", "0"),
    ("--workers", "-1"),
    ("--workers", "1000000"),
    ("--amplitude-weight", "nan"),
    ("--amplitude-weight", "-1"),
    ("--seed", "-1"),
    ("--generations", "1e9"),
    ("--generations", "99999999999"),
]:
    case(f"ident{opt}={v!r}", ID + ["--train-positions", "0.6", opt, v], "any", {"m.csv": MODES})
case(
    "ident-validate-same-as-train",
    ID + ["--train-positions", "0.6", "--validate-positions", "0.6"],
    "any",
    {"m.csv": MODES},
)
case("ident-modes-wrong-columns", ID + ["--train-positions", "0.6"], "err", {"m.csv": "a,b,c\n1,2,3\n"})
case("ident-modes-order-0", ID + ["--train-positions", "0.6"], "any", {"m.csv": "position_m,order,freq_hz\n0.6,0,30\n"})
case(
    "ident-modes-negative-freq",
    ID + ["--train-positions", "0.6"],
    "err",
    {"m.csv": "position_m,order,freq_hz\n0.6,1,-30\n"},
)
case("ident-modes-header-only", ID + ["--train-positions", "0.6"], "err", {"m.csv": "position_m,order,freq_hz\n"})
case("ident-frf-and-modes-missing", ["identify-joints", "--config", str(RCSA), "--train-positions", "0.6"], "err")
DG = ["diagnose", "--config", str(C4), str(GOOD), "--out", "{T}/d"]
for opt, v in [
    ("--jobs", "-1"),
    ("--jobs", "1000000"),
    ("--effects", "bogus"),
    ("--effects", ""),
    ("--effects", ",,"),
    ("--scheduler", "nonsense"),
    ("--scheduler", "tcp://127.0.0.1:1"),
]:
    case(f"diag{opt}={v!r}", DG + [opt, v], "err")
GB = ["gap-bench", "--out", "{T}/gb"]
for opt, v in [("--jobs", "0"), ("--jobs", "-1"), ("--cases", "bogus"), ("--cases", ""), ("--cases", ",")]:
    case(f"gapbench{opt}={v!r}", GB + [opt, v], "err")
case("gapbench-no-out", ["gap-bench", "--cases", "rigid-clean"], "err")
DM = ["demo", "--out", "{T}/demo", "--no-pace"]
for opt, v in [
    ("--stroke-mm", "-1"),
    ("--stroke-mm", "0"),
    ("--stroke-mm", "1e308"),
    ("--stroke-mm", "inf"),
    ("--feed-m-min", "0"),
    ("--feed-m-min", "-1"),
    ("--feed-m-min", "1e308"),
    ("--feed-m-min", "nan"),
]:
    case(f"demo{opt}={v!r}", DM + [opt, v], "err")

# ---------------- profile specs --------------------------------------------------------------------------------
SP = ["simulate", "--config", str(C4), "--out", "{T}/t.csv", "--duration", "0.05", "--profile"]
for spec in [
    "sine:stroke_mm=10,feed_mm_min=100,feed_mm_min=200",
    "ptp:distance_mm=5,distance_mm=5,feed_mm_min=1000",
    "chirp:amplitude_um=1,amplitude_um=1,f0_hz=1,f1_hz=10",
    "circle:radius_mm=5,radius_mm=5,feed_mm_min=100",
    "sine:stroke_mm=10,feed_mm_min=100,bogus=1",
    "step:distance_um=10,atS=0",
    "sine:stroke_mm=10mm,feed_mm_min=100",
    "step:distance_um=10um",
    "sine:stroke_mm=,feed_mm_min=100",
    "sine:",
    "step:",
    "sine:stroke_mm=10,feed_mm_min=100,",
    "sine: stroke_mm = 10 , feed_mm_min = 100",
    "SINE:stroke_mm=10,feed_mm_min=100",
    "sine:stroke_mm=-10,feed_mm_min=100",
    "sine:stroke_mm=10,feed_mm_min=0",
    "step:distance_um=0",
    "step:distance_um=1e308",
    "ptp:distance_mm=5",
    "chirp:amplitude_um=1,f0_hz=0,f1_hz=10",
    "chirp:amplitude_um=1,f0_hz=-5,f1_hz=10",
    "circle:radius_mm=0,feed_mm_min=100",
    "step:distance_um=10;at_s=0",
    "step:distance_um",
    "step:=10",
    "step:distance_um=10=20",
    "step:distance_um=0x10",
    "file:{T}/m.csv:extra",
    "sine:stroke_mm=1e-320,feed_mm_min=100",
    "step:distance_um=10,at_s=1e-320",
]:
    case(f"prof={spec}", SP + [spec], "any", {"m.csv": "t,pos\n0,0\n0.1,0.001\n"})
# file: move lists
MV = {
    "reordered": "pos,t\n0,0\n0.001,0.1\n0.002,0.2\n",
    "extra-col": "t,pos,foo\n0,0,1\n0.1,0.001,2\n0.2,0.002,3\n",
    "two-rows": "t,pos\n0,0\n0.1,0.001\n",
    "const-time": "t,pos\n0,0\n0,0.001\n0,0.002\n",
    "nan-last": "t,pos\n0,0\n0.1,0.001\n0.2,nan\n",
    "neg-time": "t,pos\n-1,0\n-0.9,0.001\n-0.8,0.002\n",
    "crlf-mid": "t,pos\n0,0\r\n0.1,0.001\n0.2,0.002\r\n",
    "tabs": "t\tpos\n0\t0\n0.1\t0.001\n",
    "semicolons": "t;pos\n0;0\n0.1;0.001\n",
    "ws-in-header": " t , pos \n0,0\n0.1,0.001\n",
    "time-huge": "t,pos\n0,0\n1e308,0.001\n",
    "time-mm-units": "t,pos\n0,0\n100,0.001\n200,0.002\n",
    "quoted": '"t","pos"\n"0","0"\n"0.1","0.001"\n',
    "uppercase": "T,POS\n0,0\n0.1,0.001\n",
    "blank-lines": "t,pos\n\n0,0\n\n0.1,0.001\n",
    "comment": "# moves\nt,pos\n0,0\n0.1,0.001\n",
    "t-starts-late": "t,pos\n5,0\n5.1,0.001\n",
    "dup-time": "t,pos\n0,0\n0.1,0.001\n0.1,0.002\n0.2,0.003\n",
    "many-cols": "t,pos,"
    + ",".join(f"c{i}" for i in range(5000))
    + "\n0,0,"
    + ",".join("0" * 5000)
    + "\n0.1,0.001,"
    + ",".join("0" * 5000)
    + "\n",
}
for n, txt in MV.items():
    case(
        f"movefile-{n}",
        ["simulate", "--config", str(C4), "--out", "{T}/t.csv", "--profile", "file:{T}/m.csv"],
        "any",
        {"m.csv": txt},
    )

# ---------------- traces for diagnose -------------------------------------------------------------------------
g = GOOD.read_text().splitlines()
hdr, rows = g[0].split(","), [r.split(",") for r in g[1:]]


def tr(h, rs, sep=",", nl="\n"):
    return nl.join(sep.join(x) for x in [h] + rs) + nl


perm = list(reversed(range(len(hdr))))
TR = {
    "reordered": tr([hdr[i] for i in perm], [[r[i] for i in perm] for r in rows]),
    "extra-cols": tr(hdr + ["foo", "bar"], [r + ["1", "2"] for r in rows]),
    "one-row": tr(hdr, rows[:1]),
    "two-rows": tr(hdr, rows[:2]),
    "const-time": tr(hdr, [["0"] + r[1:] for r in rows]),
    "nan-last-cell": tr(hdr, rows[:-1] + [rows[-1][:-1] + ["nan"]]),
    "neg-time": tr(hdr, [[str(float(r[0]) - 10)] + r[1:] for r in rows]),
    "crlf-middle": tr(hdr, rows[:150]) + tr(hdr, rows[150:], nl="\r\n").split("\r\n", 1)[1],
    "tabs": tr(hdr, rows, sep="\t"),
    "semicolons": tr(hdr, rows, sep=";"),
    "huge-cols": tr(hdr + [f"x{i}" for i in range(20000)], [r + ["0"] * 20000 for r in rows[:60]]),
    "only-t-and-cmd": tr(hdr[:2], [r[:2] for r in rows]),
    "no-pos-cmd": tr(
        [h for h in hdr if h != "pos_cmd"], [[v for h, v in zip(hdr, r, strict=False) if h != "pos_cmd"] for r in rows]
    ),
    "nan-first-cell": tr(hdr, [["nan"] + rows[0][1:]] + rows[1:]),
    "t-starts-1e9": tr(hdr, [[repr(float(r[0]) + 1e9)] + r[1:] for r in rows]),
    "all-zero-motion": tr(hdr, [[r[0]] + ["0"] * (len(r) - 1) for r in rows]),
    "pos-in-um": tr(
        hdr,
        [
            [r[0]]
            + [
                repr(float(v) * 1e6) if h.startswith("pos") or h == "motor_pos" else v
                for h, v in zip(hdr[1:], r[1:], strict=False)
            ]
            for r in rows
        ],
    ),
    "header-uppercase": tr([h.upper() for h in hdr], rows),
    "header-with-units": tr([h + " [m]" if h != "t" else h for h in hdr], rows),
    "dup-time-row": tr(hdr, rows[:100] + [rows[99]] + rows[100:]),
    "empty-cell": tr(hdr, rows[:50] + [rows[50][:3] + [""] + rows[50][4:]] + rows[51:]),
    "extra-field-in-row": tr(hdr, rows[:50] + [rows[50] + ["7"]] + rows[51:]),
    "blank-line-middle": tr(hdr, rows[:100]) + "\n" + tr(hdr, rows[100:]).split("\n", 1)[1],
    "time-in-us": tr(hdr, [[repr(float(r[0]) * 1e6)] + r[1:] for r in rows]),
    "pos-meas-scaled-2x": tr(
        hdr, [[v if h != "pos_meas" else repr(2 * float(v)) for h, v in zip(hdr, r, strict=False)] for r in rows]
    ),
}
for n, txt in TR.items():
    case(
        f"trace-{n}",
        ["diagnose", "--config", str(C4), "{T}/tr.csv", "--out", "{T}/d", "--effects", "coulomb_friction"],
        "any",
        {"tr.csv": txt},
    )
for n, sc in {
    "invalid-toml": "axis = [",
    "wrong-type": "axis = 5\n",
    "unknown-key": 'axsi = "seed004-siemens"\n',
    "binary": "\x00\x01\x02",
    "nan-value": "position_cycle_s = nan\n",
    "empty": "",
}.items():
    case(
        f"sidecar-{n}",
        ["diagnose", "--config", str(C4), "{T}/tr.csv", "--out", "{T}/d", "--effects", "coulomb_friction"],
        "any",
        {"tr.csv": GOOD.read_text(), "tr.toml": sc},
    )
case(
    "diag-holdout-same-path-twice",
    ["diagnose", "--config", str(C4), "{T}/a.csv", "{T}/a.csv", "--out", "{T}/d"],
    "err",
    {"a.csv": GOOD.read_text()},
)
case("diag-holdout-missing", DG + ["--holdout", "{T}/none.csv"], "err")

# ---------------- output paths ---------------------------------------------------------------------------------
S2 = ["simulate", "--config", str(C4), "--profile", "step:distance_um=10", "--duration", "0.02"]
case("out-tilde", S2 + ["--out", "~/badinput-should-not-exist.csv"], "any")
case("out-trailing-slash", S2 + ["--out", "{T}/t.csv/"], "err")
case("out-long-name", S2 + ["--out", "{T}/" + "a" * 300 + ".csv"], "err")
case("out-symlink-to-folder", S2 + ["--out", "{T}/lnk"], "err", {"@symlink:lnk": "{T}/sub", "@dir:sub": ""})
case(
    "out-circle-collides-json",
    [
        "simulate",
        "--config",
        str(C4),
        "--profile",
        "circle:radius_mm=5,feed_mm_min=1000",
        "--duration",
        "0.02",
        "--out",
        "{T}/t.csv",
        "--json",
        "{T}/t_x.csv",
    ],
    "err",
)
case("out-npz-suffix-upper", S2 + ["--out", "{T}/t.NPZ"], "any")
case("out-unknown-suffix", S2 + ["--out", "{T}/t.xlsx"], "any")
case("out-no-suffix", S2 + ["--out", "{T}/trace"], "any")
case("modal-json-equals-plot", ["modal", "--config", str(C4), "--json", "{T}/x", "--plot", "{T}/x"], "err")
case("rcsa-json-equals-plot", ["rcsa", "--config", str(RCSA), "--json", "{T}/x", "--plot", "{T}/x"], "err")
case(
    "ident-json-equals-write-config",
    ID + ["--train-positions", "0.6", "--json", "{T}/x.toml", "--write-config", "{T}/x.toml"],
    "err",
    {"m.csv": MODES},
)
case(
    "frf-out-is-config-folder",
    ["frf", "--config", "{T}/o/frf.csv", "--out", "{T}/o", "--force"],
    "err",
    {"o/frf.csv": C4TXT},
)
case(
    "diag-out-contains-trace",
    ["diagnose", "--config", str(C4), "{T}/d/report.json", "--out", "{T}/d", "--force"],
    "err",
    {"d/report.json": GOOD.read_text()},
)
case("out-json-long-name", S2 + ["--out", "{T}/t.csv", "--json", "{T}/" + "b" * 300 + ".json"], "err")
case("demo-out-symlink-loop", ["demo", "--out", "{T}/loop", "--no-pace"], "err", {"@symlink:loop": "{T}/loop"})

# ---------------- serve / conformance / fault ------------------------------------------------------------------
SV = ["serve", "--config", str(C4), "--can", "virtual:a18", "--duration", "0.5", "--status-interval", "0"]
for n, a in {
    "can-nocolon": ["--can", "nope"],
    "can-empty-channel": ["--can", "socketcan:"],
    "can-bogus-iface": ["--can", "bogus:x"],
    "can-missing-dev": ["--can", "socketcan:doesnotexist"],
    "can-udp-bad-group": ["--can", "udp_multicast:1.2.3.4"],
    "can-empty": ["--can", ""],
    "node-0": ["--node-id", "0"],
    "node-128": ["--node-id", "128"],
    "node--1": ["--node-id", "-1"],
    "duration--1": ["--duration", "-1"],
    "duration-nan": ["--duration", "nan"],
    "duration-inf": ["--duration", "inf"],
    "status-interval--1": ["--status-interval", "-1"],
    "status-interval-nan": ["--status-interval", "nan"],
    "bitrate--5": ["--bitrate", "-5"],
    "eds-missing": ["--eds", "{T}/none.eds"],
    "eds-is-config": ["--eds", str(C4)],
    "json-folder": ["--json", "{T}"],
    "json-proc": ["--json", "/proc/x.json"],
    "json-exists": ["--json", "{T}/exists.json"],
    "axis-dup-ids": ["--axis", f"X=1:{C4}", "--axis", f"Y=1:{C4}"],
    "axis-dup-with-main": ["--axis", f"X=1:{C4}"],
    "axis-bad-config": ["--axis", f"X=2:{C4}", "--axis", "Y=3:{T}/bad.toml"],
    "axis-spec-garbage": ["--axis", "garbage"],
    "axis-id-0": ["--axis", f"X=0:{C4}"],
    "axis-id-200": ["--axis", f"X=200:{C4}"],
    "axis-missing-config": ["--axis", "X=2:{T}/none.toml"],
    "axis-dup-names": ["--axis", f"X=2:{C4}", "--axis", f"X=3:{C4}"],
    "rt-priority-200": ["--rt-priority", "200"],
    "cpu-latency--5": ["--cpu-latency-us", "-5"],
    "latency-probe-folder": ["--latency-probe", "{T}"],
    "main-config-bad": ["--config", "{T}/bad.toml"],
}.items():
    case(
        f"serve-{n}",
        SV + a,
        "err",
        {"bad.toml": set_key(C4TXT, "mechanics", "table_mass_kg", "-5"), "exists.json": "{}"},
    )
case("serve-ok-short", SV + ["--json", "{T}/s.json"], "ok")
CF = ["conformance", "--can", "virtual:nobody", "--sdo-timeout", "0.2"]
for n, a in {
    "nobody-answers": [],
    "only-bogus": ["--only", "bogus"],
    "only-empty": ["--only", ""],
    "only-commas": ["--only", ",,"],
    "eds-missing": ["--eds", "{T}/none.eds"],
    "node-0": ["--node-id", "0"],
    "node-128": ["--node-id", "128"],
    "sdo-timeout-0": ["--sdo-timeout", "0"],
    "sdo-timeout-nan": ["--sdo-timeout", "nan"],
    "sdo-timeout--1": ["--sdo-timeout", "-1"],
    "sdo-timeout-1e308": ["--sdo-timeout", "1e308"],
    "units-0": ["--units-per-mm", "0"],
    "units-nan": ["--units-per-mm", "nan"],
    "junit-folder": ["--junit", "{T}"],
    "json-proc": ["--json", "/proc/x"],
    "can-bad": ["--can", "nope"],
    "eds-garbage": ["--eds", "{T}/g.eds"],
}.items():
    case(f"conf-{n}", CF + a, "err", {"g.eds": "garbage\x00\n[x"})
FT = ["fault", "--can", "virtual:nobody", "--timeout", "0.2"]
for n, a in {
    "status-nobody": ["status"],
    "inject-nobody": ["inject", "encoder_loss"],
    "list-nobody": ["list"],
    "clear-nobody": ["clear"],
    "node-0": ["--node-id", "0", "status"],
    "node-200": ["--node-id", "200", "status"],
    "timeout-nan": ["--timeout", "nan", "status"],
    "timeout--1": ["--timeout", "-1", "status"],
    "duty-2": ["inject", "encoder_loss", "--duty", "2"],
    "duty-nan": ["inject", "encoder_loss", "--duty", "nan"],
    "period-0": ["inject", "encoder_loss", "--period", "0"],
    "magnitude-nan": ["inject", "following_error", "--magnitude", "nan"],
    "clear-bogus": ["clear", "bogus"],
    "can-bad": ["--can", "bogus:x", "status"],
    "no-action": [],
}.items():
    case(f"fault-{n}", FT + a, "err")

# accepted (exit 0) results judged wrong by hand: the input was wrong and must not be taken silently;
# every other accepted case was judged correct (docs/bad-input.md)
JUDGED_WRONG = (
    "cfg-mechanics.lead_m=tiny",
    "cfg-control.kv_per_min=tiny",
    "cfg-friction.coulomb_n=tiny",
    "cfg-sensors.linear_scale_resolution_m=tiny",
    "cfg-control.velocity_ff_factor=tiny",
    'cfg-axis.name=""',
    "modal-positions=''",
    "modal-positions='1e-320'",
    "modal-positions='0.5,0.5'",
    "frf--fmin='1e-320'",
    "study-support-stiffness-values=''",
    "study-support-stiffness-values='5,5'",
    "study-kv-sweep-values=''",
    "study-kv-sweep-values='5,5'",
    "study-feed-sweep-values=''",
    "study-feed-sweep-values='5,5'",
    "prof=step:distance_um=10,at_s=1e-320",
    "out-tilde",
    "out-trailing-slash",
    "out-unknown-suffix",
    "serve-status-interval--1",
    "serve-status-interval-nan",
    "serve-axis-dup-names",
    "serve-json-exists",
    "diag--effects=''",
    "gapbench--cases=''",
    "trace-t-starts-1e9",
    "sidecar-wrong-type",
    "sidecar-nan-value",
    "cfg-metadata-nan",
    "cfg-drive-inf",
    "rcsa-positions=''",
)


# ---------------- running -----------------------------------------------------------------------------------------


def materialise(T: Path, files: dict):
    for name, content in files.items():
        if name.startswith("@symlink:"):
            os.symlink(content.replace("{T}", str(T)), T / name.split(":", 1)[1])
        elif name.startswith("@dir:"):
            (T / name.split(":", 1)[1]).mkdir(parents=True, exist_ok=True)
        else:
            p = T / name
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_text(content) if isinstance(content, str) else p.write_bytes(content)


def snap(T: Path):
    return {
        str(p.relative_to(T)): (p.read_bytes() if p.is_file() and not p.is_symlink() else None)
        for p in sorted(T.rglob("*"))
    }


def _child(argv, T, errf, outf):
    """In the forked child: run the CLI as `virtualaxis ARGV` would, exit with its status."""
    os.chdir(T)
    fe = os.open(errf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    fo = os.open(outf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fo, 1)
    os.dup2(fe, 2)
    sys.stdout = open(1, "w", closefd=False)
    sys.stderr = open(2, "w", closefd=False)
    import signal

    signal.signal(signal.SIGINT, signal.default_int_handler)
    rc = 1
    try:
        from virtualaxis.cli.main import main

        rc = main(argv)
    except SystemExit as e:
        rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except BaseException:
        import traceback

        traceback.print_exc()
        rc = 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(int(rc or 0) & 0xFF)


def start(c):
    cid, argv, meta = c
    T = Path(tempfile.mkdtemp(prefix="a18-"))
    materialise(T, meta["files"])
    before = snap(T)
    argv = [a.replace("{T}", str(T)) for a in argv]
    io = Path(tempfile.mkdtemp(prefix="a18io-"))
    pid = os.fork()
    if pid == 0:
        _child(argv, T, str(io / "err"), str(io / "out"))
    return {"c": c, "T": T, "before": before, "argv": argv, "io": io, "pid": pid, "t0": time.monotonic()}


def finish(job, status):
    cid, _argv, meta = job["c"]
    T = job["T"]
    if status is None:
        rc = None
    else:
        rc = os.waitstatus_to_exitcode(status)
    err = (job["io"] / "err").read_text(errors="replace")
    out = (job["io"] / "out").read_text(errors="replace")
    shutil.rmtree(job["io"], ignore_errors=True)
    dt = time.monotonic() - job["t0"]
    before = job["before"]
    after = snap(T)
    partial = [k for k in after if "partial" in k]
    changed = [k for k in before if before[k] != after.get(k, "GONE")]
    new = [k for k in after if k not in before]
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("warning:")]
    if rc is None:
        cls = "hang"
    elif "Traceback" in err or "internal error" in err:
        cls = "traceback"
    elif rc == 0:
        cls = "silent wrong" if cid in JUDGED_WRONG else "accepted"
    elif len(lines) == 1 and lines[0].startswith("error: ") and rc == 2:
        cls = "clear"
    else:
        cls = "misleading"
    if rc not in (0, None) and (new or changed or partial):
        cls += "+leftover"
    shutil.rmtree(T, ignore_errors=True)
    return {
        "id": cid,
        "argv": job["argv"],
        "rc": rc,
        "cls": cls,
        "expect": meta["expect"],
        "stderr": err[-1500:],
        "stdout": out[-600:],
        "sec": round(dt, 1),
        "new": new[:5],
        "changed": changed,
        "partial": partial,
    }


def run_all(todo, jobs, log):
    # preload what every command imports, so that each forked case costs its own work only
    import scipy.linalg
    import scipy.signal  # noqa: F401

    import virtualaxis.cli.main as m

    m.build_parser()
    for mod in (
        "virtualaxis.config",
        "virtualaxis.sim.simulator",
        "virtualaxis.sim.profiles",
        "virtualaxis.plant.modal",
        "virtualaxis.diagnosis.trace",
    ):
        try:
            __import__(mod)
        except Exception:
            pass
    try:  # load the compiled kernels once, in the parent: the forked cases inherit them
        import numpy as np

        from virtualaxis.config import load_axis_config
        from virtualaxis.sim.simulator import AxisSimulator

        AxisSimulator(load_axis_config(C4)).run_arrays(np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1))
    except Exception as exc:
        print("preload:", exc, file=sys.stderr)
    import signal

    pending, running, res = list(todo), {}, []
    while pending or running:
        while pending and len(running) < jobs:
            j = start(pending.pop(0))
            running[j["pid"]] = j
        time.sleep(0.05)
        for pid, j in list(running.items()):
            got, status = os.waitpid(pid, os.WNOHANG)
            if got == 0:
                cmd = j["argv"][0] if j["argv"] else ""
                slow = cmd in ("diagnose", "study", "rcsa", "identify-joints")
                limit = float(os.environ.get("A18_LONG", "150")) if slow else 30
                if time.monotonic() - j["t0"] > limit:
                    os.kill(pid, signal.SIGKILL)
                    os.waitpid(pid, 0)
                    r = finish(j, None)
                else:
                    continue
            else:
                r = finish(j, status)
            del running[pid]
            res.append(r)
            with open(log, "a") as fh:
                fh.write(json.dumps(r) + "\n")
    return res


if __name__ == "__main__":
    sel = sys.argv[1] if len(sys.argv) > 1 else ""
    todo = [c for c in CASES if re.search(sel, c[0])]
    if os.environ.get("A18_IDS"):
        want = set(Path(os.environ["A18_IDS"]).read_text().splitlines())
        todo = [c for c in todo if c[0] in want]
    print(f"{len(todo)} cases", file=sys.stderr)
    res = run_all(
        todo, int(os.environ.get("A18_JOBS", "3")), str(os.environ.get("A18_OUT", "/tmp/badinput-corpus.json")) + ".log"
    )
    out = Path(os.environ.get("A18_OUT", "/tmp/badinput-corpus.json"))
    out.write_text(json.dumps(res, indent=1))
    from collections import Counter

    print(Counter(r["cls"] for r in res))
    for r in res:
        if r["cls"] != "clear":
            print(f"--- {r['cls']:10s} rc={r['rc']} {r['id']}  ({r['sec']} s)")
            print("   ", r["stderr"].strip().replace("\n", "\n    ")[-700:])
