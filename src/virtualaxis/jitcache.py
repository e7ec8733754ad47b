"""Numba's on-disk cache must never fail a computation.

Every compiled function of the package is ``@njit(cache=True)``: the first process compiles it and writes the
machine code beside the module (``__pycache__/*.nbi``, ``*.nbc``); later processes load it. Numba raises when it
cannot *save* or *load* a cache entry, although the function itself compiled fine: seen in CI on a fresh clone,
where several processes (the test run, a background job, pool workers, served drives) compile at once, as
``RuntimeError: no compiled object yet for <Library '_format_block'>`` from ``Cache.save_overload``, which
failed a ``simulate`` command. Numba only tolerates such errors on Windows (``EACCES``).

:func:`install` (run on import) wraps ``Cache.save_overload`` and ``Cache.load_overload``: a failed save is
logged and skipped (the compiled function is already registered with its dispatcher, so the call goes on and the
next process compiles again); a failed load is logged and treated as a miss (the function is compiled). Neither
changes what is computed. The modules with compiled functions import this one; the reference axis
(``virtualaxis.refaxis``) does not, as it imports nothing of the package it checks (the guard is process-wide
once any other kernel module is loaded, as in the gap bench).
"""

from __future__ import annotations

import logging

from numba.core import caching

log = logging.getLogger(__name__)


def install() -> None:
    """Make numba's cache failures non-fatal (idempotent)."""
    cls = caching.Cache
    if getattr(cls, "_virtualaxis_guarded", False):
        return
    save, load = cls.save_overload, cls.load_overload

    def save_overload(self, sig, data):
        try:
            save(self, sig, data)
        except (RuntimeError, OSError, ValueError, EOFError) as exc:
            log.warning("numba cache: %s not saved (%s: %s); it stays compiled in this process",
                        getattr(self, "_name", "function"), type(exc).__name__, exc)

    def load_overload(self, sig, target_context):
        try:
            return load(self, sig, target_context)
        except Exception as exc:  # a corrupt or half-written entry of another process: compile instead
            log.warning("numba cache: %s not loaded (%s: %s); compiling it",
                        getattr(self, "_name", "function"), type(exc).__name__, exc)
            return None

    cls.save_overload = save_overload
    cls.load_overload = load_overload
    cls._virtualaxis_guarded = True


install()
