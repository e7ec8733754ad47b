"""The side channels run below the drive: each of serve's service processes (Modbus server, MQTT publisher,
OPC UA server, live-page server), with every one of its threads, at nice ``SIDE_CHANNEL_NICE``; serve's own
threads (the drive's runtime among them) at the nice serve was started with."""

from __future__ import annotations

import os
import time

import pytest
from served_drive import children, served
from services_fixtures import free_port, mosquitto  # noqa: F401 (fixture)

from virtualaxis.services.threads import SIDE_CHANNEL_NICE

pytestmark = pytest.mark.mqtt_broker


def _cmdline(pid: int) -> str:
    with open(f"/proc/{pid}/cmdline", "rb") as f:
        return f.read().replace(b"\0", b" ").decode()


def _thread_nices(pid: int) -> list[int]:
    """The nice value of each thread of process ``pid`` (/proc/PID/task/TID/stat, field 19)."""
    nices = []
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/stat") as f:
            nices.append(int(f.read().rsplit(")", 1)[1].split()[16]))
    return nices


def test_every_side_channel_process_runs_below_the_drive(mosquitto):  # noqa: F811
    with served("--modbus", "127.0.0.1:0", "--http", "127.0.0.1:0", "--opcua", f"127.0.0.1:{free_port()}",
                "--mqtt", mosquitto.url) as s:
        want = {"modbus": "virtualaxis.services.modbus", "mqtt": "virtualaxis.services.mqtt",
                "opcua": "virtualaxis.services.opcua", "http": "virtualaxis.services.http"}
        found: dict[str, int] = {}
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and len(found) < len(want):
            for child in children(s.proc.pid):
                line = _cmdline(child)
                for name, module in want.items():
                    if module in line:
                        found[name] = child
            time.sleep(0.2)
        assert set(found) == set(want), (found, [_cmdline(c) for c in children(s.proc.pid)])
        serve_nice = os.getpriority(os.PRIO_PROCESS, s.proc.pid)
        assert set(_thread_nices(s.proc.pid)) == {serve_nice}, _thread_nices(s.proc.pid)
        for name, pid in found.items():
            nices = _thread_nices(pid)
            assert len(nices) >= 1 and min(nices) >= max(SIDE_CHANNEL_NICE, serve_nice), (name, nices)
        assert s.proc.poll() is None
    assert "Traceback" not in s.stderr, s.stderr
