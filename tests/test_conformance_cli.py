"""``virtualaxis conformance`` refuses bad input with one ``error:`` line naming the option (exit 2), never a
traceback; ``--list`` prints the checks with their source, stimulus and expectation."""

from __future__ import annotations

import subprocess

from served_drive import CLI, ROOT, served

from virtualaxis.cli.main import main
from virtualaxis.conformance.suite import select


def test_bad_input_is_one_error_line(tmp_path, capsys):
    for args, needle in (
        (["--can", "bogus"], "bus 'bogus'"),
        (["--can", "virtual:x", "--only", "XYZ"], "--only 'XYZ' selects no check"),
        (["--can", "virtual:x", "--junit", str(tmp_path / "missing" / "x.xml")], "--junit"),
        (["--can", "virtual:x", "--node-id", "0"], "--node-id must be 1..127"),
        (["--can", "virtual:x", "--eds", str(tmp_path / "none.eds")], "--eds"),
        (["--can", "virtual:va-nobody-here", "--sdo-timeout", "0.1"], "does not answer"),
    ):
        code = main(["conformance", *args])
        err = capsys.readouterr().err
        assert code == 2 and needle in err and "Traceback" not in err and err.startswith("error:"), (args, err)


def test_list_names_every_check(capsys):
    assert main(["conformance", "--list"]) == 0
    out = capsys.readouterr().out
    for c in select(None):
        assert c.id in out and c.clause in out


def test_the_check_table_of_the_docs_is_the_suite():
    """docs/conformance.md lists every check of the suite, in its order, with its source, stimulus and expected
    outcome as ``--list`` prints them (a docs-only tester found 3 checks missing and 6 rows out of date)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "conformance.md").read_text()
    rows = [ln for ln in text.splitlines() if ln.startswith("| `") and ln.count(" | ") >= 4]
    want = ["| " + " | ".join(x.replace("|", "\\|") for x in (f"`{c.id}`", c.family, c.clause, c.stimulus,
                                                              c.expected)) + " |" for c in select(None)]
    assert rows[:len(want)] == want


def test_only_a_full_id_selects_that_check_alone():
    from virtualaxis.conformance.suite import select

    ids = [c.id for c in select("301-SDO-1")]
    assert ids == ["301-SDO-1"]
    assert {"301-SDO-1", "301-SDO-10", "301-SDO-11"} <= {c.id for c in select("301-SDO")}
    assert [c.id for c in select("402-FLD-1,301-SDO-1")] == [c.id for c in select(None)
                                                          if c.id in ("402-FLD-1", "301-SDO-1")]
    assert {c.family for c in select("limits")} == {"limits"}


def test_conformance_names_a_pacing_that_does_not_fit_the_node():
    """Through the user's door, both ways: `serve --lockstep` checked with `--pacing realtime`, and `serve` in
    real time checked with the default `--pacing lockstep`: one error line each, exit 2, no check run."""
    with served("--node-id", "4", "--lockstep") as lockstep_node:
        wrong = subprocess.run([*CLI, "conformance", "--can", lockstep_node.spec, "--node-id", "4", "--pacing",
                                "realtime"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert wrong.returncode == 2, wrong.stdout + wrong.stderr
    assert "node 4 waits for SYNC" in wrong.stderr and "run with --pacing lockstep" in wrong.stderr, wrong.stderr
    with served("--node-id", "4") as realtime_node:
        wrong = subprocess.run([*CLI, "conformance", "--can", realtime_node.spec, "--node-id", "4"],
                               capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert wrong.returncode == 2, wrong.stdout + wrong.stderr
    assert "node 4 keeps its own time" in wrong.stderr and "run with --pacing realtime" in wrong.stderr, wrong.stderr
    assert "summary:" not in wrong.stdout
