"""Host settings a real-time deployment makes for the drive process (Linux).

:func:`hold_cpu_latency` requests a CPU wake-up latency bound through the kernel's PM QoS interface
``/dev/cpu_dma_latency`` (as ``cyclictest`` and the ``realtime`` tuned profiles do): while the returned file
descriptor stays open, the CPU idle governor uses no idle state whose exit latency exceeds the bound. With a
bound of 0 idle CPUs poll instead of halting, which takes the wake-up from a halted CPU out of every frame's path.

Measured on this project's 2-vCPU virtual machines (cpuidle driver ``haltpoll``, guest halt-polling off; 7 axes at
1 ms SYNC, SCHED_FIFO; BENCHMARKS.md): the SDO round trip halves (~95 -> ~45 us) and the runs without a
stall had the 7th axis' SYNC -> TPDO p99 at 200-285 us in both pacing modes; but the polling vCPUs use up the
virtual machine's CPU share on its host: 10 of 47 runs with the bound had a stall of ~100 ms (of serve or of the
master: the whole guest), none of ~70 runs without it (whose worst stalls were 5-40 ms). Use it on dedicated
hardware, not on a shared virtual machine.
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
