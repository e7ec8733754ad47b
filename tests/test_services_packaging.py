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
        pytest.skip("docker-compose is not installed (a Debian package, not on PyPI; .ci/run installs it)")
    r = subprocess.run([exe, "config"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    cfg = r.stdout
    assert "eclipse-mosquitto" in cfg and "network_mode: host" in cfg and "NET_ADMIN" in cfg
    assert "socketcan:vcan0" in cfg and "--modbus" in cfg and "--mqtt" in cfg


def test_readme_documents_vcan_setup_and_compose_up():
    text = (ROOT / "README.md").read_text()
    assert "ip link add dev vcan0 type vcan" in text and "docker compose up" in text


def test_serve_side_channel_errors_are_one_line(tmp_path):
    """A Modbus port in use ends `serve` with one error line naming the address, exit 2, no traceback; bad
    option values are refused before the bus opens, naming the option or the file."""
    import argparse
    import os
    import socket
    import sys

    from virtualaxis.services.serve_options import add_arguments, prepare

    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = subprocess.run(
            [*cli, "serve", "--can", "udp_multicast:239.74.163.11,port=43917", "--duration", "1",
             "--status-interval", "0", "--modbus", f"127.0.0.1:{port}"],
            capture_output=True, text=True, timeout=120, env=env,
        )
    assert r.returncode == 2 and f"--modbus 127.0.0.1:{port}" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert "in use" in r.stderr, r.stderr  # the cause, not pymodbus' "please check address"
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    cases = [
        (["--modbus", "127.0.0.1:abc"], "--modbus '127.0.0.1:abc': port 'abc' is not a number"),
        (["--mqtt", "mqtt://127.0.0.1:1", "--mqtt-credentials", str(tmp_path / "none.toml")],
         f"--mqtt-credentials {tmp_path / 'none.toml'}: No such file"),
        (["--modbus", "999.1.1.1:5020"], "--modbus 999.1.1.1:5020: cannot resolve"),
        (["--modbus", "192.0.2.1:5020"], "--modbus 192.0.2.1:5020: cannot listen (Cannot assign requested address)"),
        (["--mqtt", "mqtt://127.0.0.1:1/path"], "has no path"),
        (["--mqtt", "mqtt://127.0.0.1:1?x=1"], "has no query"),
        (["--mqtt", "mqtt://127.0.0.1:1#frag"], "has no fragment"),
        (["--mqtt", "mqtt://127.0.0.1:1", "--telemetry-rate", "0"], "--telemetry-rate: must be > 0 and at most 1000"),
        (["--mqtt", "mqtt://127.0.0.1:1", "--telemetry-rate", "5000"], "--telemetry-rate: must be > 0"),
        (["--mqtt", "mqtt://u:pw@127.0.0.1:1"], "not accepted on the command line"),
        (["--mqtt", "http://127.0.0.1:1"], "expected mqtt://HOST:PORT"),
        (["--mqtt", "mqtt://127.0.0.1:1", "--telemetry-batch", "0"], "--telemetry-batch: must be >= 1"),
        (["--modbus-writable"], "--modbus-writable needs --modbus"),
    ]
    for argv, expect in cases:
        with pytest.raises(ValueError) as exc:
            prepare(parser.parse_args(argv), "configs/seed000-hust.toml")
        assert expect in str(exc.value), (argv, str(exc.value))
    pw_only = tmp_path / "pw.toml"
    pw_only.write_text('password = "secret"\n')
    with pytest.raises(ValueError) as exc:  # a password without a user name (MQTT 3.1.1 has none such)
        prepare(parser.parse_args(["--mqtt", "mqtt://127.0.0.1:1", "--mqtt-credentials", str(pw_only)]),
                "configs/seed000-hust.toml")
    assert "no user name" in str(exc.value) and "secret" not in str(exc.value)
    ok = prepare(parser.parse_args(["--modbus", "--mqtt", "mqtt://127.0.0.1"]), "configs/seed000-hust.toml")
    assert ok.modbus_address == ("127.0.0.1", 5020) and ok.mqtt.port == 1883 and ok.mqtt.machine == "seed000-hust"
