"""MQTT presence of `virtualaxis serve` processes on a real broker (mosquitto, or amqtt where it is absent): unique
client identities per process, a second process on the same topics named on the console, the birth sequence
and instance id in status, one stderr line per connection state change, the retained state marked not live on
a clean stop, wall-clock timestamps in telemetry. serve runs in subprocesses; a paho subscriber validates every
message against docs/schemas/.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from services_fixtures import free_port, mosquitto  # noqa: F401 (fixture)
from test_services_mqtt import Subscriber

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


class Serve:
    """`virtualaxis serve --mqtt URL` in a subprocess; its stderr lines collected as they come."""

    def __init__(self, mqtt_url: str, machine: str = "cell7"):
        env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
        self.proc = subprocess.Popen(
            [*CLI, "serve", "--can", f"udp_multicast:239.74.163.7,port={free_port()}", "--node-id", "5",
             "--machine", machine, "--mqtt", mqtt_url, "--telemetry-rate", "50", "--telemetry-batch", "5",
             "--status-interval", "0"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))

    def having(self, text: str) -> list[str]:
        return [ln for ln in list(self.lines) if text in ln]

    def wait_line(self, text: str, timeout_s: float = 60.0) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            found = self.having(text)
            if found:
                return found[0]
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        raise AssertionError(f"no stderr line with {text!r}; stderr: {self.lines[-20:]}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(timeout=5)


@pytest.mark.mqtt_broker
def test_two_serves_with_one_machine_name_keep_their_connections_and_name_the_clash(mosquitto):  # noqa: F811
    sub = Subscriber(mosquitto.port)
    a = Serve(mosquitto.url)
    b = None
    try:
        sub.wait(lambda: any(p.get("status") == "online" for p in sub.of("status")), timeout=60)
        b = Serve(mosquitto.url)
        sub.wait(lambda: len({p.get("instance_id") for p in sub.of("status") if p.get("status") == "online"}) >= 2,
                 timeout=60)
        time.sleep(3.0)  # both publish side by side
        statuses = sub.of("status")
        births = [p for p in statuses if p.get("status") == "online"]
        # no takeover: each process connected once, nobody went offline
        assert [p for p in statuses if p.get("status") == "offline"] == []
        assert len(births) == 2, [(p.get("instance_id"), p.get("birth_seq")) for p in births]
        ids = {p["instance_id"] for p in births}
        assert len(ids) == 2 and all(p["birth_seq"] == 1 for p in births)
        assert all(p["pid"] in (a.proc.pid, b.proc.pid) for p in births)
        # each console names the other process
        by_pid = {p["pid"]: p["instance_id"] for p in births}
        for me, other in ((a, b), (b, a)):
            line = me.wait_line("another process publishes", timeout_s=10)
            assert by_pid[other.proc.pid] in line and "virtualaxis/cell7/" in line and "--machine" in line
        assert a.having("connected to") and len(a.having("connected to")) == 1
        tel = sub.of("telemetry")
        assert tel and all(abs(m["ts_unix_s"] - time.time()) < 60 for m in tel)
    finally:
        a.stop()
        if b is not None:
            b.stop()
    sub.close()
    assert not sub.invalid, sub.invalid[:3]


@pytest.mark.mqtt_broker
def test_clean_stop_leaves_the_retained_state_not_live_and_the_will_pairs_with_its_birth(mosquitto):  # noqa: F811
    sub = Subscriber(mosquitto.port)
    s = Serve(mosquitto.url, machine="cell8")
    try:
        sub.wait(lambda: len(sub.of("telemetry")) >= 2, timeout=60)
        live = sub.of("state")[-1]
        assert live["online"] is True and abs(live["ts_unix_s"] - time.time()) < 60
        birth = [p for p in sub.of("status") if p.get("status") == "online"][-1]
    finally:
        s.stop()
    sub.close()
    s.wait_line("disconnected from", timeout_s=5)
    # a consumer arriving later sees the retained messages only
    late = Subscriber(mosquitto.port)
    late.wait(lambda: late.of("state") and late.of("status"), timeout=10)
    late.close()
    assert not late.invalid, late.invalid[:3]
    assert late.of("state")[-1]["online"] is False
    death = late.of("status")[-1]
    assert death["status"] == "offline"
    assert (death["instance_id"], death["birth_seq"]) == (birth["instance_id"], birth["birth_seq"])


@pytest.mark.mqtt_broker
def test_each_connection_state_change_is_one_line_on_serve_stderr(mosquitto):  # noqa: F811
    """Broker absent at start (one line however many retries), then up (connected), then killed (lost)."""
    mosquitto.stop()
    s = Serve(mosquitto.url, machine="cell9")
    try:
        first = s.wait_line("cannot connect to", timeout_s=60)
        assert f"127.0.0.1:{mosquitto.port}" in first and "axis " in first
        time.sleep(2.0)  # several retries (backoff 0.2 s doubling)
        assert len(s.having("cannot connect to")) == 1, s.lines
        mosquitto.start()
        s.wait_line("connected to", timeout_s=30)
        mosquitto.stop(kill=True)
        lost = s.wait_line("connection to", timeout_s=30)
        assert "lost" in lost and lost.count("\n") == 0
    finally:
        s.stop()
        mosquitto.start()


def test_an_untrusted_broker_certificate_is_one_line_on_serve_stderr(tmp_path):
    """mqtts:// to a TLS broker whose certificate is signed by a CA serve does not trust."""
    import shutil

    from services_fixtures import Mosquitto, readable_dir

    if shutil.which("openssl") is None:
        pytest.skip("the openssl command (makes the test CA and certificate) is not installed")
    d = readable_dir("va-mqtt-tls-")

    def ossl(*a):
        subprocess.run(["openssl", *a], cwd=d, check=True, capture_output=True)

    ossl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
         "-subj", "/CN=virtualaxis test CA")
    ossl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr",
         "-subj", "/CN=127.0.0.1")
    (d / "san.ext").write_text("subjectAltName=IP:127.0.0.1\n")
    ossl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
         "-out", "server.pem", "-days", "2", "-extfile", "san.ext")
    for f in d.iterdir():
        f.chmod(0o644)
    broker = Mosquitto(tmp_path, tls=(d / "ca.pem", d / "server.pem", d / "server.key"))
    broker.start()
    s = Serve(f"mqtts://127.0.0.1:{broker.port}", machine="cell10")
    try:
        line = s.wait_line("cannot connect to", timeout_s=60)
        assert "CERTIFICATE_VERIFY_FAILED" in line and "CA file" in line
        time.sleep(1.5)  # retries with the same reason: no further line
        assert len(s.having("cannot connect to")) == 1
    finally:
        s.stop()
        broker.cleanup()
        shutil.rmtree(d, ignore_errors=True)
