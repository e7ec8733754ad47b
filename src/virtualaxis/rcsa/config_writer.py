"""Write an axis config with identified joint values, keeping every other line of the file as it was."""

from __future__ import annotations

import re
from pathlib import Path

from virtualaxis.config import ConfigError, load_axis_config
from virtualaxis.rcsa.params import JOINT_KEYS, JOINT_SYMBOLS, JointParams, rcsa_model_from_config

_SECTION = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")


def _key_line(key: str) -> re.Pattern[str]:
    return re.compile(rf"^(\s*){re.escape(key)}\s*=")


def _replace_in_section(
    lines: list[str], section: str, key: str, new_value: str, file: str, required: bool
) -> bool:
    current = None
    pattern = _key_line(key)
    for i, line in enumerate(lines):
        m = _SECTION.match(line)
        if m:
            current = m.group(1).replace(" ", "")
            continue
        if current == section and pattern.match(line):
            indent = pattern.match(line).group(1)
            lines[i] = f"{indent}{key} = {new_value}\n"
            return True
    if required:
        raise ConfigError(
            file, f"{section}.{key}", "not found as one 'key = value' line; cannot write it back"
        )
    return False


def write_identified_config(
    source_path: str | Path, target_path: str | Path, joints: JointParams, note: str
) -> None:
    """Copy ``source_path`` to ``target_path`` with ``[rcsa.joints]`` set to ``joints`` (source = ``note``)
    and the matching plant values in ``[mechanics]`` (k_al + k_ar, k_n, k_m) when present; the result is
    loaded and validated before this returns."""
    src = str(source_path)
    try:
        lines = Path(source_path).read_text(encoding="utf-8").splitlines(keepends=True)
    except OSError as exc:
        raise ConfigError(src, "", f"cannot read ({exc.strerror})") from None
    note_toml = note.replace("\\", "\\\\").replace('"', '\\"')
    for key, sym in zip(JOINT_KEYS, JOINT_SYMBOLS, strict=True):
        val = getattr(joints, sym)
        _replace_in_section(
            lines, "rcsa.joints", key, f'{{ value = {val:.6g}, source = "{note_toml}: {sym}" }}', src, True
        )
    plant = {
        "bearing_axial_stiffness_n_per_m": (joints.k_al + joints.k_ar, "k_al + k_ar"),
        "nut_contact_stiffness_n_per_m": (joints.k_n, "k_n"),
        "coupling_stiffness_nm_per_rad": (joints.k_m, "k_m"),
    }
    for key, (val, what) in plant.items():
        _replace_in_section(
            lines, "mechanics", key, f'{{ value = {val:.6g}, source = "{note_toml}: {what}" }}', src, False
        )
    Path(target_path).write_text("".join(lines), encoding="utf-8")
    cfg = load_axis_config(target_path)
    rcsa_model_from_config(cfg)
