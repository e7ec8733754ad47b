"""Host settings a real-time deployment makes for the drive process (Linux).

:func:`hold_cpu_latency` requests a CPU wake-up latency bound through the kernel's PM QoS interface
``/dev/cpu_dma_latency`` (as ``cyclictest`` and the ``realtime`` tuned profiles do): while the returned file
descriptor stays open, the CPU idle governor uses no idle state whose exit latency exceeds the bound. On this
project's 2-vCPU virtual machines (cpuidle driver ``haltpoll``) a bound of 0 us keeps idle CPUs polling instead of
halting, which removes the VM-exit wake-up from every frame's path: with 7 axes at 1 ms SYNC, SCHED_FIFO, the
7th axis' SYNC -> TPDO p99 went from 350-700 us (lockstep 470-820) to ~260-290 us in both pacing modes
(BENCHMARKS.md, issue #15). The price: idle CPUs spin while the request is held (power, and a shared host's
other guests).
"""

from __future__ import annotations

import os
import struct

CPU_DMA_LATENCY = "/dev/cpu_dma_latency"
MAX_LATENCY_US = 2_000_000_000  # the kernel's "no constraint" value (PM_QOS_CPU_LATENCY_DEFAULT_VALUE)


class HostSettingError(Exception):
    """A host setting that could not be made (the message names the file and the reason)."""


def hold_cpu_latency(latency_us: int, path: str = CPU_DMA_LATENCY) -> int:
    """Request a CPU wake-up latency bound of ``latency_us`` [us] (0 = never leave the polling idle state);
    returns the file descriptor that holds the request (closing it, or the process ending, drops it)."""
    if isinstance(latency_us, bool) or not isinstance(latency_us, int) or not 0 <= latency_us <= MAX_LATENCY_US:
        raise HostSettingError(f"CPU latency bound must be an integer 0..{MAX_LATENCY_US} us (got {latency_us!r})")
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as exc:
        raise HostSettingError(f"{path}: cannot open it to request a CPU latency bound ({exc.strerror})") from None
    try:
        os.write(fd, struct.pack("i", latency_us))
    except OSError as exc:
        os.close(fd)
        raise HostSettingError(f"{path}: the CPU latency request was refused ({exc.strerror})") from None
    return fd


def current_cpu_latency_us(path: str = CPU_DMA_LATENCY) -> int:
    """The bound in force now (the smallest of all open requests; ``MAX_LATENCY_US`` when none) [us]."""
    with open(path, "rb") as f:
        return struct.unpack("i", f.read(4))[0]
