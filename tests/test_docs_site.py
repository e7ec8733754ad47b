"""The documentation site: the generated reference pages are those the code generates now, and
``mkdocs build --strict`` (broken links, pages missing from the nav, stale anchors fail) builds it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from virtualaxis import docs_reference

ROOT = Path(__file__).resolve().parents[1]


def test_generated_reference_pages_are_current():
    stale = [name for name, render in docs_reference.PAGES.items()
             if (ROOT / "docs" / "reference" / name).read_text() != render()]
    assert not stale, f"stale: {stale}; run python3 -m virtualaxis.docs_reference --write docs/reference"


def test_check_names_a_stale_page(tmp_path, capsys):
    for name, render in docs_reference.PAGES.items():
        (tmp_path / name).write_text(render())
    assert docs_reference.main(["--check", str(tmp_path)]) == 0
    (tmp_path / "cli.md").write_text("# edited by hand\n")
    assert docs_reference.main(["--check", str(tmp_path)]) == 1
    assert "cli.md" in capsys.readouterr().err


def test_site_builds_strict_with_no_broken_link(tmp_path):
    if shutil.which("mkdocs") is None and subprocess.run([sys.executable, "-m", "mkdocs", "--version"],
                                                         capture_output=True).returncode != 0:
        pytest.skip("mkdocs is not installed (a dev dependency: pip install -e '.[dev]')")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "site" / "tutorials" / "controller-test" / "index.html").is_file()
