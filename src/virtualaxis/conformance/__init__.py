"""CiA 301 / CiA 402 conformance checks run by a CANopen master against any node (docs/conformance.md).

    from virtualaxis.conformance import run_conformance
    results = run_conformance(network, node_id=1)            # a connected canopen.Network
"""

from __future__ import annotations

from virtualaxis.conformance.runner import REGISTRY, Check, Context, Result, run_checks, summary
from virtualaxis.conformance.suite import select


def run_conformance(network, node_id: int, *, eds: str | None = None, only: str | None = None,
                    units_per_mm: float = 1000.0, sdo_timeout_s: float = 1.0, progress=None,
                    pacing: str = "lockstep") -> list[Result]:
    """Run the selected checks (all by default) against ``node_id`` on ``network``; returns the results.
    ``pacing``: "lockstep" (the node advances on SYNC; each SYNC waits for its answer) or "realtime"."""
    if pacing not in ("lockstep", "realtime"):
        raise ValueError(f"pacing must be 'lockstep' or 'realtime' (got {pacing!r})")
    from virtualaxis.master import DEFAULT_EDS

    ctx = Context(network, node_id, eds or DEFAULT_EDS, sdo_timeout_s=sdo_timeout_s, units_per_mm=units_per_mm,
                  lockstep=pacing == "lockstep")
    checks = select(only)
    try:
        return run_checks(ctx, checks, progress=progress)
    finally:
        ctx.stop_sync()


__all__ = ["REGISTRY", "Check", "Context", "Result", "run_checks", "run_conformance", "select", "summary"]
