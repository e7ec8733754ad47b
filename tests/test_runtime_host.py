"""`serve --cpu-latency-us`: the PM QoS CPU latency request a real-time host makes (runtime/host.py)."""

from __future__ import annotations

import os
import subprocess

import pytest
from served_drive import CLI, ROOT, served

from virtualaxis.runtime.host import (
    CPU_DMA_LATENCY,
    MAX_LATENCY_US,
    HostSettingError,
    current_cpu_latency_us,
    hold_cpu_latency,
)

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile


def _qos_usable() -> bool:
    try:
        os.close(os.open(CPU_DMA_LATENCY, os.O_WRONLY))
        return True
    except OSError:
        return False


needs_qos = pytest.mark.skipif(not _qos_usable(), reason=f"{CPU_DMA_LATENCY} cannot be opened for writing here "
                                                         "(no PM QoS device, or not root)")


@needs_qos
def test_request_is_in_force_while_held_and_dropped_when_closed():
    before = current_cpu_latency_us()
    fd = hold_cpu_latency(3)
    try:
        assert current_cpu_latency_us() == min(3, before)
    finally:
        os.close(fd)
    assert current_cpu_latency_us() == before


@pytest.mark.parametrize("bad", [-1, MAX_LATENCY_US + 1, 2.5, True, "0"])
def test_bad_bound_is_refused_with_the_range(bad):
    with pytest.raises(HostSettingError, match=r"0\.\.2000000000 us"):
        hold_cpu_latency(bad)


def test_unopenable_device_names_the_file(tmp_path):
    with pytest.raises(HostSettingError, match=str(tmp_path / "missing")):
        hold_cpu_latency(0, str(tmp_path / "missing"))


def test_serve_refuses_a_negative_bound_without_a_traceback():
    proc = subprocess.run([*CLI, "serve", "--can", "virtual:host-test", "--cpu-latency-us", "-5",
                           "--duration", "0.2"], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert proc.returncode != 0
    assert "--cpu-latency-us" in proc.stderr and "Traceback" not in proc.stderr


@needs_qos
def test_serve_holds_the_bound_while_serving_and_drops_it_at_exit():
    before = current_cpu_latency_us()
    with served("--cpu-latency-us", "0") as s:
        assert current_cpu_latency_us() == 0
    assert s.returncode == 0, s.stderr
    assert current_cpu_latency_us() == before
