"""The suite: the checks of :mod:`~virtualaxis.conformance.checks_301` and
:mod:`~virtualaxis.conformance.checks_402`, registered by importing them, and the choice of some of them. The
runner knows how to run a check, not which checks there are."""

from __future__ import annotations

from virtualaxis.conformance import checks_301, checks_402  # noqa: F401 - registers the checks
from virtualaxis.conformance.runner import REGISTRY, Check


def select(ids: str | None) -> list[Check]:
    """Checks whose id or family matches one of the comma-separated patterns (prefix match); all without."""
    if not ids:
        return list(REGISTRY)
    pats = [p.strip() for p in ids.split(",") if p.strip()]
    return [c for c in REGISTRY if any(c.id == p or c.id.startswith(p) or c.family == p for p in pats)]
