"""The suite: the checks of :mod:`~virtualaxis.conformance.checks_301` and
:mod:`~virtualaxis.conformance.checks_402`, registered by importing them, and the choice of some of them. The
runner knows how to run a check, not which checks there are."""

from __future__ import annotations

from virtualaxis.conformance import checks_301, checks_402  # noqa: F401 - registers the checks
from virtualaxis.conformance.runner import REGISTRY, Check


def select(ids: str | None) -> list[Check]:
    """Checks whose id or family matches one of the comma-separated patterns; all without. A pattern that is a
    check's id selects that check alone (``301-SDO-1``, not ``301-SDO-10``); any other is an id prefix
    (``301-SDO``) or a family."""
    if not ids:
        return list(REGISTRY)
    pats = [p.strip() for p in ids.split(",") if p.strip()]
    known = {c.id for c in REGISTRY}
    exact = {p for p in pats if p in known}
    prefixes = [p for p in pats if p not in known]
    return [c for c in REGISTRY if c.id in exact or c.family in prefixes
            or any(c.id.startswith(p) for p in prefixes)]
