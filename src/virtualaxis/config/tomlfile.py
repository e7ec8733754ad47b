"""TOML text parsed with the checks every reader of a user's TOML file needs (configs, trace sidecars, MQTT
credentials): a syntax error with the parser's line and column, and a bound on nesting — tables and arrays
inside each other thousands of levels deep exhaust the parser's recursion (``RecursionError``) or every
recursive reader after it, and no file this package reads nests deeper than a few levels."""

from __future__ import annotations

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

#: deepest nesting of tables / arrays accepted (a config nests 3 levels: section, value table, unit)
MAX_TOML_DEPTH = 32


class TomlError(ValueError):
    """A TOML text that cannot be used: ``str()`` says why (without the file name; the caller adds it)."""


def _depth(data: object) -> int:
    """Nesting depth of dicts and lists (iterative: no recursion limit of its own)."""
    deepest = 0
    stack: list[tuple[object, int]] = [(data, 0)]
    while stack:
        node, d = stack.pop()
        if isinstance(node, dict):
            children = list(node.values())
        elif isinstance(node, list):
            children = node
        else:
            continue
        deepest = max(deepest, d + 1)
        if deepest > MAX_TOML_DEPTH:
            return deepest
        stack.extend((c, d + 1) for c in children)
    return deepest


def parse_toml(text: str) -> dict:
    """``tomllib.loads(text)``; raises :class:`TomlError` for invalid TOML or nesting deeper than
    :data:`MAX_TOML_DEPTH` levels."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TomlError(f"not valid TOML: {exc}") from None
    except RecursionError:
        raise TomlError(f"not usable TOML: tables or arrays nested too deeply (at most {MAX_TOML_DEPTH} levels "
                        "are read)") from None
    if _depth(data) > MAX_TOML_DEPTH:
        raise TomlError(f"not usable TOML: tables or arrays nested more than {MAX_TOML_DEPTH} levels deep")
    return data
