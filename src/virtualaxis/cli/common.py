"""Helpers shared by CLI commands."""

from __future__ import annotations

import sys
from contextlib import contextmanager

from tqdm import tqdm


def add_config_argument(p, required: bool = True) -> None:
    p.add_argument("--config", required=required, help="axis config TOML (configs/*.toml)")


@contextmanager
def progress(total: int, desc: str):
    """A tqdm bar on stderr, silent when stderr is not a terminal and the job is short."""
    bar = tqdm(total=total, desc=desc, unit="cyc", unit_scale=True, file=sys.stderr, leave=False,
               disable=None, mininterval=0.5)
    try:
        yield bar
    finally:
        bar.close()


def parse_float_list(text: str, name: str, hint: str = "", what: str = "value") -> list[float]:
    """'0.1,0.5,0.9' -> [0.1, 0.5, 0.9]; a CliError naming the option on an empty list or item, text, NaN/inf,
    a subnormal number (1e-320: a typo, never a position or a gain) or a value given twice."""
    import math
    import sys

    from virtualaxis.cli.errors import CliError

    if not text.strip():
        raise CliError(f"{name}: empty list; give comma-separated numbers{hint} or leave the option out")
    vals = []
    for item in (x.strip() for x in text.split(",")):
        try:
            v = float(item)
        except ValueError:
            raise CliError(f"{name}: not a number: {item!r}{hint}") from None
        if not math.isfinite(v):
            raise CliError(f"{name}: not a finite number: {item!r}")
        if v != 0 and abs(v) < sys.float_info.min:
            raise CliError(f"{name}: {item!r} is a subnormal number (below 2.2e-308 in magnitude); give 0 or a "
                           "real value")
        if v in vals:
            raise CliError(f"{name}: duplicate {what} {item!r} (given twice)")
        vals.append(v)
    return vals


#: memory one worker process of a fit pool may take [bytes]: measured 415 MiB for the main process and 850 MiB
#: for main + 2 workers (``diagnose --jobs 2`` of a 120 000-row trace, docs/bad-input.md), ~220 MiB per worker
WORKER_MEMORY_BYTES = 256 * 2**20
#: worker processes per usable CPU at most (more only share the CPUs and cost memory)
WORKERS_PER_CPU = 2


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of /proc/meminfo [bytes]; None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def max_workers() -> tuple[int, str]:
    """The most worker processes this machine runs sensibly, and why: :data:`WORKERS_PER_CPU` per usable CPU,
    and no more than the available memory holds at :data:`WORKER_MEMORY_BYTES` each (at least 1)."""
    cpus = usable_cpus()
    limit = WORKERS_PER_CPU * cpus
    why = f"{cpus} usable CPU(s), {WORKERS_PER_CPU} workers per CPU"
    mem = available_memory_bytes()
    if mem is not None:
        by_mem = max(1, mem // WORKER_MEMORY_BYTES)
        why += f"; {mem / 2**30:.1f} GiB of memory available, ~{WORKER_MEMORY_BYTES >> 20} MiB per worker"
        limit = min(limit, by_mem)
    return max(1, limit), why


def check_jobs(value: int | None, option: str = "--jobs", default: int = 2) -> int:
    """A worker-pool size option checked before any work: 1 .. :func:`max_workers`. Left out (None): ``default``,
    lowered to what the machine runs."""
    from virtualaxis.cli.errors import CliError

    limit, why = max_workers()
    if value is None:
        return min(default, limit)
    if value < 1:
        raise CliError(f"{option} must be >= 1 (got {value})")
    if value > limit:
        raise CliError(f"{option} {value}: at most {limit} worker processes on this machine ({why})")
    return value


def check_node_options(node_id: int, timeout_s: float) -> None:
    """``--node-id`` and ``--timeout`` of a command that talks to one node; a ``CliError`` naming the option."""
    from virtualaxis.cli.errors import CliError

    if not 1 <= node_id <= 127:
        raise CliError(f"--node-id must be 1..127 (got {node_id})")
    if not 0.001 <= timeout_s <= 60:  # (also refuses nan: every comparison with nan is false)
        raise CliError(f"--timeout must be 0.001..60 s (got {timeout_s})")


def open_remote_node(can: str, node_id: int, timeout_s: float):
    """``(network, node)``: a ``canopen`` master on the bus string ``can`` with the remote node ``node_id``
    (the shipped EDS), its SDO client bounded (short frames and transfers that never end are errors, not hangs
    or crashes) with a response timeout of ``timeout_s``. Bad options and a bus that does not open are a
    ``CliError``; the caller disconnects the network."""
    import logging

    import canopen

    from virtualaxis.cli.errors import CliError
    from virtualaxis.master import DEFAULT_EDS, connect, install_bounded_sdo
    from virtualaxis.runtime import BusOpenError

    check_node_options(node_id, timeout_s)
    logging.getLogger("canopen").setLevel(logging.CRITICAL)  # its SDO timeouts are reported by us, once
    try:
        net = connect(can)
    except BusOpenError as exc:
        raise CliError(str(exc)) from None
    try:
        node = canopen.RemoteNode(node_id, DEFAULT_EDS)
        install_bounded_sdo(node)
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        net.add_node(node)
    except BaseException:
        net.disconnect()
        raise
    return net, node
