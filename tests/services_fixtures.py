"""Fixtures of the side-channel tests: a real ``mosquitto`` broker (Debian package) on a free loopback port,
with its own config file (listener 127.0.0.1 only, no persistence), that a test can stop, kill and restart.

Imported by tests/test_services_*.py (``from services_fixtures import mosquitto``).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout_s: float = 5.0, *, open_: bool = True) -> None:
    end = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                ok = True
        except OSError:
            ok = False
        if ok == open_:
            return
        if time.monotonic() > end:
            raise AssertionError(f"port {port} did not {'open' if open_ else 'close'} in {timeout_s} s")
        time.sleep(0.01)


class Mosquitto:
    """A mosquitto process on 127.0.0.1:``port`` with a config of its own."""

    def __init__(self, workdir: Path, port: int | None = None, extra_conf: str = ""):
        sbin = "/usr/sbin/mosquitto"
        self.exe = shutil.which("mosquitto") or (sbin if os.path.exists(sbin) else None)
        if self.exe is None:
            raise RuntimeError("mosquitto is not installed (apt-get install -y mosquitto; .ci/run does this)")
        self.port = port or free_port()
        self.conf = workdir / "mosquitto.conf"
        self.log = workdir / "mosquitto.log"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            "allow_anonymous true\n"
            "persistence false\n"
            "log_dest stderr\n"
            "log_type error\n"
            "log_type warning\n" + extra_conf
        )
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def start(self) -> Mosquitto:
        self._log = open(self.log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=self._log, stderr=self._log)
        self.starts += 1
        try:
            wait_port(self.port)
        except AssertionError:
            self.stop()
            raise AssertionError(f"mosquitto did not start: {self.log.read_text()[-2000:]}") from None
        return self

    def stop(self, *, kill: bool = False) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL if kill else signal.SIGTERM)
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self.proc = None
        self._log.close()

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"


@pytest.fixture
def mosquitto(tmp_path):
    broker = Mosquitto(tmp_path).start()
    yield broker
    broker.stop()
