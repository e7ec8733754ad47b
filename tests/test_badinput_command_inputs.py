"""Bad input of the commands: serve / conformance outputs and inputs, the served EDS, bus options,
side-channel options, identify-joints, simulate, diagnose sidecars and traces). Each case runs through the real
CLI (``main([...])`` in-process) and must exit 2 with ONE ``error:`` line naming the file or option, leaving
every file of its folder unchanged; see docs/bad-input.md."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from virtualaxis.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
C0 = ROOT / "configs" / "seed000-hust.toml"
C4 = ROOT / "configs" / "seed004-siemens.toml"
EDS = ROOT / "eds" / "virtualaxis.eds"
TRACES = ROOT / "tests" / "badinput" / "traces"
C2 = ROOT / "configs" / "seed002-usst.toml"
IJ = ["identify-joints", "--config", str(C2), "--train-positions", "0.6,1.0", "--generations", "2", "--population",
      "5", "--workers", "1", "--json", "{T}/ij.json"]
SERVE = ["serve", "--status-interval", "0", "--duration", "1"]
DIAG = ["diagnose", "--config", str(C4), "--out", "{T}/d", "--effects", "coulomb_friction", "--no-hybrid",
        "--jobs", "1"]


def _setup(tmp: Path) -> None:
    (tmp / "c.toml").write_text(C0.read_text())
    (tmp / "e.eds").write_text(EDS.read_text())
    os.symlink(tmp / "c.toml", tmp / "link.toml")
    os.link(tmp / "e.eds", tmp / "hard.eds")
    (tmp / "old.npz").write_bytes(b"old probe")
    (tmp / "empty.eds").write_text("")
    text = EDS.read_text()
    (tmp / "no6040.eds").write_text(_drop_object(text, 0x6040))
    (tmp / "no1005.eds").write_text(_drop_object(text, 0x1005))
    (tmp / "no_device_info.eds").write_text(text.replace("[DeviceInfo]", "[DeviceInformation]"))
    modes = "position_m,order,freq_hz,amplitude_m_per_n\n" + "".join(
        f"{pos},{k + 1},{f}," + "\n" for pos in (0.6, 1.0) for k, f in enumerate((24, 118, 540, 720)))
    (tmp / "modes.csv").write_text(modes)
    (tmp / "modes_off_screw.csv").write_text(modes + "9.6,1,24,\n")
    (tmp / "frf_flat.csv").write_text("position_m,freq_hz,re,im\n" + "".join(
        f"{pos},{5 + 0.5 * i},1e-7,-3e-10\n" for pos in (0.6, 1.0) for i in range(20)))
    good = (TRACES / "good.csv").read_bytes()
    (tmp / "no_header.csv").write_bytes(good.split(b"\n", 1)[1])
    for name, side in (("ctl_neg", "[controller]\nkv_per_min = -5\n"),
                       ("ctl_quoted_str", '[controller]\n"control.kv_per_min" = "fast"\n'),
                       ("ctl_nested_huge", "[controller.control]\nkv_per_min = 1e300\n"),
                       ("ctl_twice", '[controller]\nkv_per_min = 40\n"control.kv_per_min" = 50\n')):
        (tmp / f"{name}.csv").write_bytes(good)
        (tmp / f"{name}.toml").write_text(side)


def _drop_object(text: str, index: int) -> str:
    """The EDS without the sections of one object (``[6040]``, ``[6040subN]``)."""
    import re

    parts = re.split(r"(?m)^(?=\[)", text)
    return "".join(p for p in parts if not re.match(rf"\[{index:04X}(sub[0-9A-Fa-f]+)?\]", p, re.I))


def _snapshot(tmp: Path) -> dict[str, bytes | None]:
    return {str(p.relative_to(tmp)): (p.read_bytes() if p.is_file() and not p.is_symlink() else None)
            for p in sorted(tmp.rglob("*"))}


CASES: list[tuple[str, list[str], list[str]]] = [
    # ---- serve / conformance outputs are checked like every other command's (cli/outputs.py)
    ("serve-json-is-config", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--json", "{T}/c.toml",
                              "--force"], ["--json", "c.toml", "also an input"]),
    ("serve-json-is-config-via-symlink", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--json",
                                          "{T}/link.toml", "--force"], ["--json", "link.toml", "also an input"]),
    ("serve-json-is-eds-via-hard-link", [*SERVE, "--config", "{T}/c.toml", "--eds", "{T}/e.eds", "--can",
                                         "virtual:s27", "--json", "{T}/hard.eds", "--force"],
     ["--json", "hard.eds", "also an input"]),
    ("serve-probe-is-config", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--latency-probe",
                               "{T}/c.toml"], ["--latency-probe", "c.toml", "also an input"]),
    ("serve-probe-exists", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--latency-probe",
                            "{T}/old.npz"], ["--latency-probe", "old.npz exists", "--force"]),
    ("serve-json-is-probe", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--json", "{T}/same.npz",
                             "--latency-probe", "{T}/same.npz"], ["--latency-probe", "also the output of --json"]),
    ("serve-probe-not-npz", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--latency-probe",
                             "{T}/x.txt"], ["--latency-probe", "x.txt", ".npz"]),
    # ---- the served EDS has what the slave and the drive need (before: KeyError (4101, 0) after
    # canopen's warning printed twice; an EDS without the Controlword was served, exit 0)
    ("serve-eds-empty", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--eds", "{T}/empty.eds"],
     ["empty.eds", "not an EDS"]),
    ("serve-eds-no-device-info", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--eds",
                                  "{T}/no_device_info.eds"], ["no_device_info.eds", "[DeviceInfo]"]),
    ("serve-eds-no-1005", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--eds", "{T}/no1005.eds"],
     ["no1005.eds", "0x1005:00", "COB-ID SYNC"]),
    ("serve-eds-no-controlword", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--eds",
                                  "{T}/no6040.eds"], ["no6040.eds", "0x6040:00", "controlword", "RPDO1"]),
    # ---- bus option values parsed and named (before: internal error 'required argument is not an
    # integer' at bus.py:263; virtual:x,bitrate=abc served)
    ("serve-can-hop-limit-not-int", [*SERVE, "--config", "{T}/c.toml", "--can",
                                     "udp_multicast:239.74.163.99,hop_limit=abc"], ["hop_limit='abc'", "integer"]),
    ("serve-can-port-out-of-range", [*SERVE, "--config", "{T}/c.toml", "--can",
                                     "udp_multicast:239.74.163.99,hop_limit=0,port=99999"], ["port=99999", "1..65535"]),
    ("serve-can-virtual-unknown-option", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27,bitrate=abc"],
     ["'bitrate'", "virtual bus", "accepted"]),
    # ---- a sidecar's [controller] values are checked and reported against the sidecar (before: the
    # axis config file was named; quoted "control.*" keys were ignored with a warning, their values unchecked)
    ("diag-sidecar-controller-negative", DIAG + ["{T}/ctl_neg.csv"],
     ["ctl_neg.toml", "[controller] control.kv_per_min", ">= 0"]),
    ("diag-sidecar-controller-quoted-key-string", DIAG + ["{T}/ctl_quoted_str.csv"],
     ["ctl_quoted_str.toml", "control.kv_per_min", "must be a number"]),
    ("diag-sidecar-controller-nested-huge", DIAG + ["{T}/ctl_nested_huge.csv"],
     ["ctl_nested_huge.toml", "control.kv_per_min", "plausible range"]),
    ("diag-sidecar-controller-key-twice", DIAG + ["{T}/ctl_twice.csv"], ["ctl_twice.toml", "given twice"]),
    # ---- side-channel options consistent (before: --telemetry-rate 5000 accepted without --mqtt, --machine ''
    # replaced by the config's name)
    ("serve-telemetry-rate-without-mqtt", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27",
                                           "--telemetry-rate", "5000"], ["--telemetry-rate", "--mqtt"]),
    ("serve-machine-empty", [*SERVE, "--config", "{T}/c.toml", "--can", "virtual:s27", "--mqtt",
                             "mqtt://127.0.0.1:1", "--machine", ""], ["--machine", "empty"]),
    # ---- identify-joints (before: the weight silently dropped; a row at 9.6 m on a 2.6 m screw
    # silently ignored; 8 'note:' lines before the error)
    ("ij-frequencies-only-and-weight", IJ + ["--modes", "{T}/modes.csv", "--frequencies-only", "--amplitude-weight",
                                             "0.5"], ["--frequencies-only", "--amplitude-weight", "alternatives"]),
    ("ij-modes-row-off-the-screw", IJ + ["--modes", "{T}/modes_off_screw.csv"],
     ["modes_off_screw.csv", "9.6", "outside the screw"]),
    ("ij-frf-without-peaks", IJ + ["--frf", "{T}/frf_flat.csv"], ["frf_flat.csv", "no natural frequency"]),
    # ---- conformance --only '' meant "all checks"
    ("conformance-only-empty", ["conformance", "--can", "virtual:nobody", "--only", ""], ["--only", "empty"]),
    # ---- simulate (before: ptp accel 1e9 / jerk 1e12 commanded 100 m/s^2 per position cycle against a 5 m/s^2
    # limit, exit 0; a step of 0 um ran while other kinds refuse 0)
    ("sim-ptp-acceleration-over-the-limit", ["simulate", "--config", str(C4), "--profile",
                                            "ptp:distance_mm=100,feed_mm_min=6000,accel_m_s2=1e9,jerk_m_s3=1e12",
                                            "--out", "{T}/t.csv"], ["peak acceleration", "max_acceleration_m_s2"]),
    ("sim-step-zero", ["simulate", "--config", str(C4), "--profile", "step:distance_um=0", "--out", "{T}/t.csv"],
     ["distance_um", "must not be 0"]),
    # ---- a trace without its header row (before: 'row 1: column 0: duplicate column name')
    ("diag-trace-no-header", DIAG + ["{T}/no_header.csv"], ["no_header.csv", "row 1", "header row is missing"]),
    # ---- an unknown option is the command's error, with its help (before: the top level's)
    ("conformance-unknown-option", ["conformance", "--bogus"],
     ["error: virtualaxis conformance: unrecognized arguments: --bogus", "virtualaxis conformance --help"]),
    ("conformance-json-is-eds", ["conformance", "--can", "virtual:nobody", "--eds", "{T}/e.eds", "--json",
                                 "{T}/hard.eds", "--force"], ["--json", "hard.eds", "also an input"]),
]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("argv,want", [pytest.param(a, w, id=i) for i, a, w in CASES])
def test_bad_input_gives_one_clear_line(tmp_path, capsys, argv, want):
    _setup(tmp_path)
    before = _snapshot(tmp_path)
    rc = main([a.replace("{T}", str(tmp_path)) for a in argv])
    cap = capsys.readouterr()
    lines = [ln for ln in cap.err.splitlines() if ln.strip()]
    assert rc == 2, f"exit {rc}, stderr: {cap.err}"
    assert "ready:" not in cap.out, cap.out  # refused before anything was served
    assert "Traceback" not in cap.err and "internal error" not in cap.err, cap.err
    assert len(lines) == 1 and lines[0].startswith("error: "), cap.err
    for w in want:
        assert w.replace("{T}", str(tmp_path)) in lines[0], (w, lines[0])
    assert _snapshot(tmp_path) == before  # inputs unchanged, nothing written


def test_unknown_sidecar_key_is_reported(tmp_path):
    """a top-level sidecar key the diagnosis does not read (``sample_rate_hz = 500``) was ignored silently;
    now a warning of the trace (printed before the conclusion and kept in report.json)."""
    from virtualaxis.diagnosis.trace import read_trace

    (tmp_path / "t.csv").write_bytes((TRACES / "good.csv").read_bytes())
    (tmp_path / "t.toml").write_text('sample_rate_hz = 500\nnotes = "x"\n')
    tr = read_trace(tmp_path / "t.csv")
    assert [w for w in tr.warnings if "t.toml" in w and "not used: sample_rate_hz (" in w], tr.warnings


def test_cr_only_line_ends_keep_the_last_row(tmp_path):
    """CR-only line ends (old Mac style) were read, but the complete last row was dropped with a 'file looks
    truncated' warning; now the trace reads as with LF line ends, no warning."""
    import numpy as np

    from virtualaxis.diagnosis.trace import read_trace

    text = (TRACES / "good.csv").read_text()
    assert text.endswith("\n")
    (tmp_path / "cr.csv").write_text(text.replace("\n", "\r"), newline="")
    ref = read_trace(TRACES / "good.csv")
    cr = read_trace(tmp_path / "cr.csv")
    assert cr.t.size == ref.t.size and np.array_equal(cr.pos_cmd, ref.pos_cmd)
    assert not [w for w in cr.warnings if "truncated" in w], cr.warnings
