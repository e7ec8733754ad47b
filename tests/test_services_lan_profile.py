"""The `lan` deployment (deploy/lan/, compose profile `lan`): the shipped mosquitto.conf and acl run on a real
mosquitto (listener moved to a free loopback port, files to a temporary folder); `virtualaxis serve` with a
credentials file publishes through it, a dashboard user can read but not command or overwrite, anonymous
clients are refused."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from services_fixtures import free_port, readable_dir, wait_port

ROOT = Path(__file__).resolve().parents[1]
LAN = ROOT / "deploy" / "lan"
USERS = {"virtualaxis": "pw-va", "dashboard": "pw-dash", "testctl": "pw-ctl"}


@pytest.fixture
def lan_broker(tmp_path):
    exe = shutil.which("mosquitto")
    if exe is None:
        pytest.skip("mosquitto is not installed (the lan profile's broker)")
    d = readable_dir("va-lan-")
    passwd = d / "passwd"
    for i, (user, pw) in enumerate(USERS.items()):
        subprocess.run(["mosquitto_passwd", *(["-c"] if i == 0 else []), "-b", str(passwd), user, pw],
                       check=True, capture_output=True)
    shutil.copy(LAN / "acl", d / "acl")
    for f in (passwd, d / "acl"):
        f.chmod(0o644)
    port = free_port()
    conf = (LAN / "mosquitto.conf").read_text()
    assert "listener 1883 0.0.0.0" in conf and "allow_anonymous false" in conf
    conf = conf.replace("listener 1883 0.0.0.0", f"listener {port} 127.0.0.1").replace("/mosquitto/config", str(d))
    (d / "mosquitto.conf").write_text(conf)
    proc = subprocess.Popen([exe, "-c", str(d / "mosquitto.conf")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        wait_port(port)
        yield port
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def _client(port: int, user: str | None, name: str) -> tuple[mqtt.Client, list, threading.Event, list]:
    msgs: list = []
    rcs: list = []
    connected = threading.Event()
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"{name}-{os.getpid()}",
                    protocol=mqtt.MQTTv5)
    if user:
        c.username_pw_set(user, USERS[user])

    def on_connect(cl, u, flags, rc, props):
        rcs.append(rc.value)
        if rc.value == 0:
            cl.subscribe("virtualaxis/#", qos=1)
        connected.set()

    c.on_connect = on_connect
    c.on_message = lambda cl, u, m: msgs.append((m.topic, bytes(m.payload), m.retain))
    c.connect("127.0.0.1", port, keepalive=5)
    c.loop_start()
    assert connected.wait(10)
    return c, msgs, connected, rcs


def _wait(pred, timeout_s: float = 60.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError("condition not reached")


@pytest.mark.mqtt_broker
def test_lan_profile_authenticates_and_keeps_dashboards_read_only(lan_broker, tmp_path):
    port = lan_broker
    anon, _, _, anon_rc = _client(port, None, "anon")
    assert anon_rc and anon_rc[0] != 0  # anonymous refused
    anon.loop_stop()
    creds = tmp_path / "creds.toml"
    creds.write_text(f'username = "virtualaxis"\npassword = "{USERS["virtualaxis"]}"\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    cli = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]
    serve = subprocess.Popen(
        [*cli, "serve", "--can", f"udp_multicast:239.74.163.11,port={free_port()}", "--node-id", "4",
         "--machine", "lan1", "--mqtt", f"mqtt://127.0.0.1:{port}", "--mqtt-credentials", str(creds),
         "--allow-fault-injection", "--status-interval", "0"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    dash, dmsgs, _, drc = _client(port, "dashboard", "dash")
    ctl, cmsgs, _, crc = _client(port, "testctl", "ctl")
    try:
        assert drc == [0] and crc == [0]
        _wait(lambda: any(t.endswith("/state") for t, _, _ in dmsgs))
        status_topic = next(t for t, _, _ in dmsgs if t.endswith("/status"))
        base = status_topic.rsplit("/", 1)[0]
        # the dashboard user: its command and its overwrite of the retained status are dropped by the ACL
        dash.publish(f"{base}/fault/set", json.dumps({"action": "clear", "kind": "all", "id": "dash"}), qos=1)
        dash.publish(status_topic, json.dumps({"status": "offline"}), qos=1, retain=True)
        # the test controller's command is delivered and answered
        ctl.publish(f"{base}/fault/set", json.dumps({"action": "clear", "kind": "all", "id": "ctl"}), qos=1)
        _wait(lambda: any(t.endswith("/fault/result") and b'"ctl"' in p for t, p, _ in cmsgs), timeout_s=20)
        time.sleep(1.0)
        results = [p for t, p, _ in cmsgs if t.endswith("/fault/result")]
        assert not any(b'"dash"' in p for p in results)
        assert not any(t == status_topic and b'"online"' not in p for t, p, _ in dmsgs)
    finally:
        for c in (dash, ctl):
            c.loop_stop()
            c.disconnect()
        serve.terminate()
        serve.wait(timeout=30)
    err = serve.stderr.read()
    assert "connected to" in err and "Traceback" not in err, err[-2000:]
