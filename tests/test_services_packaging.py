"""docker-compose.yml is valid (Debian's docker-compose, as in CI), the Dockerfile installs the package with
exactly the README's install step, and the README documents the vcan set-up and `docker compose up`."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def readme_install_steps() -> list[str]:
    """The pip install commands of the README's first bash block (the README's way to install)."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S)
    assert block, "README.md: no ```bash block with the install command"
    steps = []
    for line in block.group(1).splitlines():
        for part in line.split("&&"):
            if "pip install" in part:
                steps.append(part.strip())
    assert steps, "README.md: the first bash block has no pip install step"
    return steps


def dockerfile_run_steps() -> list[str]:
    lines = (ROOT / "Dockerfile").read_text().splitlines()
    return [ln[len("RUN ") :].strip() for ln in lines if ln.startswith("RUN ")]


def test_dockerfile_installs_the_package_the_readme_way():
    runs = dockerfile_run_steps()
    pip_runs = [r for r in runs if "pip install" in r]
    assert pip_runs == readme_install_steps(), f"Dockerfile RUN {pip_runs} != README install {readme_install_steps()}"
    text = (ROOT / "Dockerfile").read_text()
    assert "COPY . ." in text and 'ENTRYPOINT ["virtualaxis"]' in text


def test_docker_compose_file_is_valid_and_wires_the_emulator_to_the_host():
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.fail("docker-compose is not installed (.ci/run installs Debian's docker-compose)")
    r = subprocess.run([exe, "config"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    cfg = r.stdout
    assert "eclipse-mosquitto" in cfg and "network_mode: host" in cfg and "NET_ADMIN" in cfg
    assert "socketcan:vcan0" in cfg and "--modbus" in cfg and "--mqtt" in cfg


def test_readme_documents_vcan_setup_and_compose_up():
    text = (ROOT / "README.md").read_text()
    assert "ip link add dev vcan0 type vcan" in text and "docker compose up" in text
