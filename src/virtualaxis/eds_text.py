"""The text of an EDS file where the ``canopen`` package does not read it: ``LowLimit`` / ``HighLimit`` as
written (``canopen`` parses integer limits only). Shared by the CiA 301 stack's object dictionary and the
drive's object table, which both enforce these limits; neither depends on the other for it."""

from __future__ import annotations

from configparser import RawConfigParser
from pathlib import Path


def object_key(section: str) -> tuple[int, int] | None:
    """``(index, sub)`` of an object section name (``6040``, ``1400sub5``; any case), ``None`` for others
    (``FileInfo``, ``MandatoryObjects``, ...)."""
    name = section.lower()
    try:
        if len(name) == 4:
            return int(name, 16), 0
        if len(name) > 7 and name[4:7] == "sub":
            return int(name[:4], 16), int(name[7:], 16)
    except ValueError:
        return None
    return None


def declared_limits(eds_path: str | Path) -> dict[tuple[int, int], tuple[str | None, str | None, str | None]]:
    """Every object section with a ``LowLimit`` or ``HighLimit``: ``(index, sub)`` -> (low text, high text,
    ``DataType`` text), ``None`` where a key is absent or empty. The caller converts them by the data type and
    decides what a malformed one means."""
    parser = RawConfigParser(inline_comment_prefixes=(";",))
    parser.optionxform = str  # type: ignore[assignment, method-assign]
    parser.read(eds_path, encoding="utf-8")
    out: dict[tuple[int, int], tuple[str | None, str | None, str | None]] = {}
    for section in parser.sections():
        key = object_key(section)
        if key is None:
            continue
        low, high, data_type = (parser.get(section, option, fallback="").strip() or None
                                for option in ("LowLimit", "HighLimit", "DataType"))
        if low is not None or high is not None:
            out[key] = (low, high, data_type)
    return out
