"""Every fenced python block of README.md and docs/**/*.md runs as written.

Fence info strings (the text after the opening three backticks):

- ``python`` — run as is (``python -c``, working directory = the repository root); it must exit 0.
- ``python serve: ARGS`` — run while ``virtualaxis serve --can udp_multicast:... ARGS`` serves a drive in
  another process. The snippet uses the documented bus string ``udp_multicast:239.74.163.2``; the test swaps
  it (everywhere in the snippet) for a private group and port, so that tests running at the same time do not
  hear each other.
- ``python pytest: FILE`` — a test file of a tutorial: written as FILE into an empty folder and run there with
  ``python -m pytest`` (the pytest plugin loaded as an installed package loads it); every test must pass.
- ``python no-run: REASON`` — not run (an API summary with placeholders, a signature list); the reason is
  required.

A failure names the file and line of the block and shows the block and the end of its output.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from served_drive import ROOT, served

from virtualaxis.runtime.bus import DEFAULT_UDP_GROUP

DOCUMENTED_BUS = f"udp_multicast:{DEFAULT_UDP_GROUP}"
FENCE = re.compile(r"^(```+|~~~+)\s*(.*)$")
SNIPPET_TIMEOUT_S = 120


@dataclass(frozen=True)
class Snippet:
    file: str  # relative to the repository root
    line: int  # line of the opening fence (1-based)
    info: str  # the fence's info string
    code: str

    @property
    def id(self) -> str:
        return f"{self.file}:{self.line}"

    @property
    def language(self) -> str:
        return self.info.split(":", 1)[0].split()[0].lower() if self.info.strip() else ""

    def attribute(self) -> tuple[str, str]:
        """("", "") / ("no-run", reason) / ("serve", args) from ``python ATTR: VALUE``."""
        rest = self.info.strip()[len(self.info.strip().split()[0]):].strip() if self.info.strip() else ""
        if not rest:
            return "", ""
        key, _, value = rest.partition(":")
        return key.strip().lower(), value.strip()


def doc_files() -> list[Path]:
    root = Path(ROOT)
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def extract(path: Path) -> list[Snippet]:
    """The fenced blocks of one markdown file (any language), in order."""
    out = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        fence, info, start = m.group(1), m.group(2), i
        body = []
        i += 1
        while i < len(lines) and not lines[i].startswith(fence):
            body.append(lines[i])
            i += 1
        out.append(Snippet(str(path.relative_to(ROOT)), start + 1, info, "\n".join(body) + "\n"))
        i += 1
    return out


PYTHON = [s for f in doc_files() for s in extract(f) if s.language in ("python", "py", "python3")]


def _report(snippet: Snippet, what: str, proc: subprocess.CompletedProcess | None = None) -> str:
    numbered = "\n".join(f"{n:4d} | {line}" for n, line in enumerate(snippet.code.splitlines(), start=1))
    msg = f"{snippet.id}: python block (fence `{snippet.info}`) {what}\n--- block ---\n{numbered}"
    if proc is not None:
        tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-30:])
        msg += f"\n--- output (last 30 lines) ---\n{tail}"
    return msg


def _run(snippet: Snippet, code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MPLBACKEND": "Agg"}
    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env,
                              timeout=SNIPPET_TIMEOUT_S)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        pytest.fail(_report(snippet, f"did not finish in {SNIPPET_TIMEOUT_S} s",
                            subprocess.CompletedProcess(exc.cmd, -1, out, err)))


def run_pytest_snippet(snippet: Snippet, folder: Path, code: str | None = None,
                       args: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """Write a ``python pytest: FILE`` block (or ``code``) as FILE into ``folder`` and run pytest on it there."""
    import importlib.metadata

    name = snippet.attribute()[1]
    assert name.endswith(".py") and "/" not in name, _report(snippet, f"pytest: wants a file name (got {name!r})")
    (folder / name).write_text(snippet.code if code is None else code)
    plugin = [] if "virtualaxis" in {ep.name for ep in importlib.metadata.entry_points(group="pytest11")} else [
        "-p", "virtualaxis.testing"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (str(Path(ROOT) / "src"),
                                                                    os.environ.get("PYTHONPATH", "")) if p))
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", *plugin, name,
                           *args], capture_output=True, text=True, cwd=folder, env=env, timeout=300)


def test_docs_have_python_snippets():
    assert len(PYTHON) >= 3, [s.id for s in PYTHON]  # the extraction works (a broken regex would skip all)


@pytest.mark.parametrize("snippet", [
    # a block that talks to a served drive is timing-sensitive (e.g. the SYNC-jitter frame log of canopen.md)
    pytest.param(s, id=s.id, marks=[pytest.mark.exclusive] if s.attribute()[0] == "serve" else [])
    for s in PYTHON])
def test_python_snippet_runs_as_written(snippet: Snippet, tmp_path: Path):
    key, value = snippet.attribute()
    if key == "no-run":
        assert value, _report(snippet, "is marked no-run without a reason (write `python no-run: WHY`)")
        pytest.skip(f"no-run: {value}")
    if key == "serve":
        assert DOCUMENTED_BUS in snippet.code, _report(
            snippet, f"is marked serve: but does not use the documented bus string {DOCUMENTED_BUS!r}")
        with served(*shlex.split(value)) as srv:
            proc = _run(snippet, snippet.code.replace(DOCUMENTED_BUS, srv.spec))
        assert proc.returncode == 0, _report(snippet, f"exited {proc.returncode} (drive served: serve {value})",
                                             proc)
        return
    if key == "pytest":
        proc = run_pytest_snippet(snippet, tmp_path)
        assert proc.returncode == 0, _report(snippet, f"pytest exited {proc.returncode}", proc)
        return
    assert key == "", _report(snippet, f"has an unknown fence attribute {key!r} (use serve:, pytest: or no-run:)")
    proc = _run(snippet, snippet.code)
    assert proc.returncode == 0, _report(snippet, f"exited {proc.returncode}", proc)


def test_the_first_csp_master_runs_again_against_the_same_drive():
    """docs/tutorials/first-csp-master.md: its master, run three times against one `serve`, passes each time (it
    leaves the axis at rest and starts with a fault reset; a master that left the axis moving failed every later
    run with a following-error fault)."""
    path = Path(ROOT) / "docs" / "tutorials" / "first-csp-master.md"
    (snippet,) = [s for s in extract(path) if s.attribute()[0] == "serve"]
    with served(*shlex.split(snippet.attribute()[1])) as srv:
        code = snippet.code.replace(DOCUMENTED_BUS, srv.spec)
        for run in range(3):
            proc = _run(snippet, code)
            assert proc.returncode == 0, _report(snippet, f"run {run + 1} of 3 exited {proc.returncode}", proc)
            assert "following error" in proc.stdout
