"""``calibrated.toml``: the input config's own text with only the diagnosed values changed.

Each changed ``section.key`` is edited on its line: a plain ``key = 1.5  # comment`` keeps its comment, an inline
table ``key = { value = 1.5, source = "..." }`` gets the new value and the diagnosis as its source (a ``unit``
is dropped: the written value is in SI). A key the input does not have is added at the end of its section (a
section it does not have, at the end of the file). Everything else — order, comments, blank lines, the keys the
diagnosis did not change — stays as the user wrote it."""

from __future__ import annotations

import difflib
import json
import math
import re

_SECTION = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\-]+)\s*\]\s*(#.*)?$")
_KEY = re.compile(r"^(\s*)([A-Za-z0-9_\-]+)(\s*=\s*)(.*)$")


def toml_scalar(v) -> str:
    """One TOML value: floats round-trip exactly."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    return json.dumps(str(v))


def _split_comment(rhs: str) -> tuple[str, str]:
    """(value text, trailing comment with its leading spaces) of a plain value; strings may hold '#'."""
    in_str: str | None = None
    for i, ch in enumerate(rhs):
        if in_str:
            if ch == in_str and rhs[i - 1] != "\\":
                in_str = None
        elif ch in "\"'":
            in_str = ch
        elif ch == "#":
            j = i
            while j > 0 and rhs[j - 1] in " \t":
                j -= 1
            return rhs[:j], rhs[j:]
    return rhs.rstrip(), rhs[len(rhs.rstrip()):]


def _new_rhs(old_rhs: str, value, source: str | None) -> str:
    val, comment = _split_comment(old_rhs)
    if val.lstrip().startswith("{") and "unit" not in val:
        # inline table: replace its value (and source)
        new = re.sub(r"(\bvalue\s*=\s*)([^,}]+?)(\s*[,}])", lambda m: m.group(1) + toml_scalar(value) + m.group(3),
                     val, count=1)
        if source is not None:
            if re.search(r"\bsource\s*=", new):
                new = re.sub(r'(\bsource\s*=\s*)("(?:[^"\\]|\\.)*"|\'[^\']*\')',
                             lambda m: m.group(1) + toml_scalar(source), new, count=1)
            else:
                new = re.sub(r"\s*}\s*$", f", source = {toml_scalar(source)} }}", new, count=1)
        return new + comment
    if source is not None and not isinstance(value, (bool, str)):
        return f"{{ value = {toml_scalar(value)}, source = {toml_scalar(source)} }}" + comment
    return toml_scalar(value) + comment


def edit_config_text(text: str, changes: dict[str, object], sources: dict[str, str] | None = None) -> str:
    """``text`` (a config file) with each ``changes["section.key"]`` written in place (see the module doc)."""
    sources = sources or {}
    lines = text.splitlines(keepends=True)
    todo = dict(changes)
    section = ""
    last_line_of: dict[str, int] = {}  # section -> index of its last key line (or its header)
    for i, line in enumerate(lines):
        body = line.rstrip("\r\n")
        m = _SECTION.match(body)
        if m:
            section = m.group(1)
            last_line_of[section] = i
            continue
        m = _KEY.match(body)
        if not m:
            continue
        if section:
            last_line_of[section] = i
        key = f"{section}.{m.group(2)}"
        if key in todo:
            value = todo.pop(key)
            eol = line[len(body):]
            lines[i] = m.group(1) + m.group(2) + m.group(3) + _new_rhs(m.group(4), value, sources.get(key)) + eol
    if todo:
        if lines and not lines[-1].endswith("\n"):
            lines[-1] += "\n"
        inserts: dict[int, list[str]] = {}
        new_sections: dict[str, list[str]] = {}
        for key, value in todo.items():
            sec, name = key.rsplit(".", 1)
            rhs = _new_rhs("0", value, sources.get(key))
            if sec in last_line_of:
                inserts.setdefault(last_line_of[sec], []).append(f"{name} = {rhs}\n")
            else:
                new_sections.setdefault(sec, []).append(f"{name} = {rhs}\n")
        for idx in sorted(inserts, reverse=True):
            lines[idx + 1:idx + 1] = inserts[idx]
        for sec, items in new_sections.items():
            lines.append(f"\n[{sec}]\n")
            lines.extend(items)
    return "".join(lines)


def text_diff(old: str, new: str, old_name: str, new_name: str) -> list[str]:
    """Line diff (unified, no context) of two config texts."""
    return [ln.rstrip("\n") for ln in difflib.unified_diff(old.splitlines(keepends=True), new.splitlines(keepends=True),
                                                          old_name, new_name, n=0)]
