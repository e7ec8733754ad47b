"""The Docker image and docker-compose.yml: the image is a runtime install (no test tools) run by a non-root user,
with a healthcheck that asks the drive (`virtualaxis health`); the compose file is valid (Debian's
docker-compose, as in CI) with a vcan profile on the host's SocketCAN and a ci profile on the host-local
udp_multicast bus with fault injection; the README documents both."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def dockerfile_run_steps() -> list[str]:
    lines = (ROOT / "Dockerfile").read_text().splitlines()
    return [ln[len("RUN ") :].strip() for ln in lines if ln.startswith("RUN ")]


def test_dockerfile_is_a_runtime_install_run_by_a_user_with_a_drive_healthcheck():
    pip_runs = [r for r in dockerfile_run_steps() if "pip install" in r]
    assert len(pip_runs) == 1 and re.search(r"pip install (--no-cache-dir )?\. ", pip_runs[0] + " "), pip_runs
    assert "[dev]" not in pip_runs[0] and "-e" not in pip_runs[0].split()
    text = (ROOT / "Dockerfile").read_text()
    users = re.findall(r"^USER (\S+)", text, re.M)
    assert users and users[-1] not in ("root", "0"), users
    health = re.search(r"^HEALTHCHECK .*?CMD (.*)$", text.replace("\\\n", " "), re.M)
    assert health and "virtualaxis health" in health.group(1), health
    assert "COPY . ." in text and 'ENTRYPOINT ["virtualaxis"]' in text


def _compose(*args: str) -> str:
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("docker-compose is not installed (a Debian package, not on PyPI; .ci/run installs it)")
    r = subprocess.run([exe, *args, "config"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_docker_compose_file_is_valid_with_a_vcan_and_a_ci_profile():
    import yaml

    _compose()
    for profile in ("vcan", "ci"):
        _compose("--profile", profile)
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    assert services["mosquitto"]["image"].startswith("eclipse-mosquitto")
    drives = [s for s in services.values() if not str(s.get("image", "")).startswith("eclipse-mosquitto")]
    vcan = [s for s in drives if "vcan" in s.get("profiles", [])]
    ci = [s for s in drives if "ci" in s.get("profiles", [])]
    assert len(vcan) == 1 and len(ci) == 1
    v, c = vcan[0], ci[0]
    assert v["network_mode"] == "host" and "NET_ADMIN" in v["cap_add"] and "socketcan:vcan0" in v["command"]
    assert c["network_mode"] == "host" and "cap_add" not in c
    bus = c["command"][c["command"].index("--can") + 1]
    assert bus.startswith("udp_multicast:") and "--allow-fault-injection" in c["command"]
    assert c["environment"]["VIRTUALAXIS_CAN"] == bus  # the healthcheck asks on the bus the drive is served on
    assert v["environment"]["VIRTUALAXIS_CAN"] == "socketcan:vcan0"
    for svc in (v, c):
        assert "--modbus" in svc["command"] and "--mqtt" in svc["command"]


def test_health_answers_for_a_served_drive_and_fails_for_a_silent_node():
    import sys

    from served_drive import served

    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    env = {**__import__("os").environ, "PYTHONPATH": str(ROOT / "src")}
    with served("--node-id", "3") as srv:
        ok = subprocess.run([*cli, "health", "--can", srv.spec, "--node-id", "3"], capture_output=True, text=True,
                            timeout=60, env=env)
        silent = subprocess.run([*cli, "health", "--can", srv.spec, "--node-id", "4", "--timeout", "0.3"],
                                capture_output=True, text=True, timeout=60, env=env)
    assert ok.returncode == 0 and ok.stdout.startswith("ok: node 3 answers, statusword 0x"), ok.stdout + ok.stderr
    assert silent.returncode == 1 and "Traceback" not in silent.stderr, silent.stderr
    lines = silent.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "node 4" in lines[0], silent.stderr


def test_readme_documents_vcan_setup_and_compose_up():
    text = (ROOT / "README.md").read_text()
    assert "ip link add dev vcan0 type vcan" in text
    assert "docker compose --profile vcan up" in text and "docker compose --profile ci up" in text


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
         f"--mqtt-credentials {tmp_path / 'none.toml'}: credentials file not found"),
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
