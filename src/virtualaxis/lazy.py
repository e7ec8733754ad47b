"""Lazy package exports: a package ``__init__`` names what it exports and the module defining each name; the
module is imported when the name is first read (PEP 562 module ``__getattr__``).

So ``import virtualaxis.drive.injection`` loads the injection constants without the drive's compiled kernel, and
``virtualaxis --help`` does not load numba or scipy; ``from virtualaxis.drive import Drive`` is unchanged.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, exports: dict[str, str], namespace: dict[str, Any]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for the package ``package`` whose globals are ``namespace``: ``exports`` maps
    each exported name to the module that defines it. A name read once is kept in ``namespace``."""

    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *exports})

    return __getattr__, __dir__
