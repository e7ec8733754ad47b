"""Fixtures of the side-channel tests: a real MQTT broker on a free loopback port that a test can stop, kill and
restart. The broker is ``mosquitto`` where it is on PATH (Debian package) and otherwise amqtt, a pure-Python
broker that ``pip install -e ".[dev]"`` brings (``tests/amqtt_broker.py``); ``VIRTUALAXIS_TEST_BROKER=amqtt`` or
``=mosquitto`` chooses one. Both listen on 127.0.0.1 only, without persistence, optionally with a password file
(``users``) and a TLS listener (``tls``).

Imported by tests/test_services_*.py (``from services_fixtures import mosquitto``).
"""

from __future__ import annotations

import json
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
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


BROKER_ENV = "VIRTUALAXIS_TEST_BROKER"
AMQTT_SCRIPT = Path(__file__).resolve().parent / "amqtt_broker.py"


def mosquitto_exe() -> str | None:
    """The mosquitto executable on PATH, None if absent (.ci/run hides it from PATH to test on amqtt)."""
    return shutil.which("mosquitto")


def broker_wanted() -> str:
    """The environment's choice of broker as given (lower case; "" for none), not yet checked."""
    return os.environ.get(BROKER_ENV, "").strip().lower()


def broker_kind(want: str | None = None) -> str:
    """'mosquitto' or 'amqtt': ``want``, else the environment's choice, else mosquitto where it is installed."""
    want = (want or broker_wanted()).strip().lower()
    if want not in ("", "mosquitto", "amqtt"):
        raise RuntimeError(f"{BROKER_ENV}={want!r}: expected mosquitto or amqtt")
    if want == "mosquitto" and mosquitto_exe() is None:
        raise RuntimeError(f"{BROKER_ENV}=mosquitto but mosquitto is not installed")
    return want or ("mosquitto" if mosquitto_exe() else "amqtt")


def readable_dir(prefix: str) -> Path:
    """A temporary folder readable by everyone (mosquitto started as root reads its files as user 'mosquitto')."""
    d = Path(tempfile.mkdtemp(prefix=prefix))
    d.chmod(0o755)
    return d


class MqttBroker:
    """An MQTT broker process on 127.0.0.1:``port`` with a config of its own (mosquitto or amqtt, see
    ``broker_kind``). ``users``: user name -> password, anonymous clients refused; ``tls``: (CA, certificate,
    key) PEM files, the listener then speaks TLS only."""

    def __init__(self, workdir: Path, port: int | None = None, *, users: dict[str, str] | None = None,
                 tls: tuple[Path, Path, Path] | None = None, kind: str | None = None):
        self.kind = broker_kind(kind)
        self.mqtt5 = self.kind == "mosquitto"  # amqtt 0.12 speaks MQTT 3.1.1 only
        self.port = port or free_port()
        self.log = workdir / f"{self.kind}.log"
        self._files = readable_dir("va-mqtt-broker-")
        if self.kind == "mosquitto":
            self.conf = workdir / "mosquitto.conf"
            lines = [f"listener {self.port} 127.0.0.1", f"allow_anonymous {'false' if users else 'true'}",
                     "persistence false", "log_dest stderr", "log_type error", "log_type warning"]
            if users:
                lines.append(f"password_file {self._mosquitto_passwords(users)}")
            if tls:
                lines += [f"cafile {tls[0]}", f"certfile {tls[1]}", f"keyfile {tls[2]}"]
            self.conf.write_text("\n".join(lines) + "\n")
            self.argv = [mosquitto_exe(), "-c", str(self.conf)]
        else:
            self.conf = workdir / "amqtt.json"
            listener: dict = {"type": "tcp", "bind": f"127.0.0.1:{self.port}"}
            if tls:
                listener.update(ssl=True, cafile=str(tls[0]), certfile=str(tls[1]), keyfile=str(tls[2]))
            plugins: dict = {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": not users}}
            if users:
                plugins["amqtt.plugins.authentication.FileAuthPlugin"] = {
                    "password_file": str(self._amqtt_passwords(users))}
            self.conf.write_text(json.dumps({"listeners": {"default": listener}, "plugins": plugins}))
            self.argv = [sys.executable, str(AMQTT_SCRIPT), str(self.conf)]
        self.proc: subprocess.Popen | None = None
        self.starts = 0

    def _mosquitto_passwords(self, users: dict[str, str]) -> Path:
        passwd = shutil.which("mosquitto_passwd") or "/usr/bin/mosquitto_passwd"
        pwfile = self._files / "passwd"
        for i, (user, password) in enumerate(users.items()):
            subprocess.run([passwd, *(["-c"] if i == 0 else []), "-b", str(pwfile), user, password],
                           check=True, capture_output=True)
        os.chmod(pwfile, 0o600)
        if os.geteuid() == 0:  # mosquitto started as root drops to the user 'mosquitto': it must read the file
            try:
                owner = pwd.getpwnam("mosquitto")
                os.chown(pwfile, owner.pw_uid, owner.pw_gid)
            except KeyError:
                pass
        return pwfile

    def _amqtt_passwords(self, users: dict[str, str]) -> Path:
        from pwdlib.hashers.argon2 import Argon2Hasher

        pwfile = self._files / "passwd"
        hasher = Argon2Hasher(time_cost=1, memory_cost=1024, parallelism=1)  # cheap to verify on a loaded host
        pwfile.write_text("".join(f"{u}:{hasher.hash(p)}\n" for u, p in users.items()))
        return pwfile

    def start(self) -> MqttBroker:
        self._log = open(self.log, "ab")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(self.argv, stdout=self._log, stderr=self._log)
        self.starts += 1
        try:
            wait_port(self.port, timeout_s=15.0)
        except AssertionError:
            self.stop()
            raise AssertionError(f"{self.kind} did not start: {self.log.read_text()[-2000:]}") from None
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

    def cleanup(self) -> None:
        """Stop the broker and remove its password file."""
        self.stop()
        shutil.rmtree(self._files, ignore_errors=True)

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"


Mosquitto = MqttBroker  # the name the side-channel tests import


@pytest.fixture
def mqtt_broker(request, tmp_path):
    """The broker of ``broker_kind()``; a test parametrised indirectly (:data:`ON_BOTH_BROKERS`) gets the kind it
    names."""
    broker = MqttBroker(tmp_path, kind=getattr(request, "param", None)).start()
    yield broker
    broker.cleanup()


mosquitto = mqtt_broker  # the fixture name the side-channel tests use

#: ``@ON_BOTH_BROKERS`` on a test taking the ``mosquitto`` fixture: it runs on the environment's broker and on
#: amqtt, the pure-Python broker a machine without mosquitto gets (MQTT 3.1.1 only); amqtt alone where mosquitto
#: is not installed. For the tests that cover what a broker changes: the protocol version, the retained state,
#: the last will, commands and their answers.
ON_BOTH_BROKERS = pytest.mark.parametrize(
    "mosquitto", [None, "amqtt"] if mosquitto_exe() and broker_wanted() != "amqtt" else [None], indirect=True,
    ids=lambda kind: kind or "broker")
