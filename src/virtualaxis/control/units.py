"""Unit conversions of machine-tool control (SINUMERIK conventions, docs/reference/siemens-conventions.md)."""

from __future__ import annotations

import math

PER_S_PER_1000_PER_MIN = 1000.0 / 60.0  # 1 (1000/min) = 16.667 1/s: Kv = 1 -> 1 mm error at 1 m/min


def kv_1000_per_min_to_per_s(kv_1000_per_min: float) -> float:
    return kv_1000_per_min * PER_S_PER_1000_PER_MIN


def kv_per_s_to_1000_per_min(kv_per_s: float) -> float:
    return kv_per_s / PER_S_PER_1000_PER_MIN


def kv_per_min_to_per_s(kv_per_min: float) -> float:
    return kv_per_min / 60.0


def mm_per_min_to_m_per_s(feed_mm_per_min: float) -> float:
    return feed_mm_per_min / 60000.0


def rpm_to_rad_s(rpm: float) -> float:
    return rpm * 2.0 * math.pi / 60.0


def rad_s_to_rpm(rad_s: float) -> float:
    return rad_s * 60.0 / (2.0 * math.pi)
