"""The published numbers of seed 002 that the reproduction is compared against (not model outputs).

Positions l1..l6 [m] (Sec. 4.1); measured natural frequencies [Hz] (Tables 1, 4, 6-9, NaN = the
paper's "—" at l4); measured amplitudes (Table 2, printed in "m", read as m/N); identified joint
parameters (Tables 3 and 5); the paper's own predictions (Tables 4, 6-9).
"""

from __future__ import annotations

import numpy as np

from virtualaxis.rcsa.identify import MeasuredModes
from virtualaxis.rcsa.params import JointParams

NAN = float("nan")
POSITIONS_M = {"l1": 0.6, "l2": 0.8, "l3": 1.0, "l4": 1.3, "l5": 1.6, "l6": 1.9}

# Tables 1 (l1, l3, l5) and 4/8/9 (l2, l4, l6), "Measured" rows
MEASURED_FREQUENCIES_HZ = {
    "l1": (24.0, 118.0, 523.0, 716.0),
    "l2": (24.0, 117.0, 536.0, 713.0),
    "l3": (24.0, 116.0, 565.0, 721.0),
    "l4": (24.0, 116.0, NAN, 717.0),
    "l5": (23.0, 113.0, 561.0, 728.0),
    "l6": (23.0, 112.0, 528.0, 712.0),
}
# Table 2 (only the training positions)
MEASURED_AMPLITUDES_M_PER_N = {
    "l1": (2.44e-4, 2.62e-5, 4.13e-7, 2.24e-7),
    "l3": (3.70e-4, 3.06e-5, 4.06e-7, 2.91e-7),
    "l5": (3.54e-4, 3.61e-5, 3.71e-7, 2.51e-7),
}

# Table 3 = Table 5 "multi-position"; Table 5 single-position columns
TABLE3_MULTI_POSITION = JointParams(4.28e7, 2.94e7, 7.09e8, 5.53e3, 2.02e3, 2.73e3, 2.25e5, 3.50)
TABLE5_L3_SINGLE = JointParams(4.17e7, 3.12e7, 7.32e8, 5.61e3, 2.42e3, 2.33e3, 4.25e3, 3.44)
TABLE5_L5_SINGLE = JointParams(1.07e7, 6.05e7, 9.08e8, 5.53e3, 1.94e3, 2.32e3, 2.55e3, 3.55)

# the paper's predicted natural frequencies [Hz]
PAPER_PREDICTED_HZ = {
    "multi": {  # Table 4 (held out) and Tables 6/7 "multi-position" rows
        "l2": (24.0, 116.0, 549.0, 719.0),
        "l3": (23.0, 115.0, 577.0, 719.0),
        "l4": (24.0, 115.0, NAN, 720.0),
        "l5": (23.0, 115.0, 573.0, 736.0),
        "l6": (23.0, 114.0, 534.0, 733.0),
    },
    "l3": {  # Table 6 and Table 8
        "l2": (24.0, 116.0, 550.0, 723.0),
        "l3": (24.0, 116.0, 576.0, 723.0),
        "l4": (24.0, 116.0, NAN, 726.0),
        "l6": (23.0, 115.0, 535.0, 736.0),
    },
    "l5": {  # Table 7 and Table 9
        "l2": (23.0, 108.0, 558.0, 766.0),
        "l4": (23.0, 112.0, NAN, 745.0),
        "l5": (23.0, 113.0, 571.0, 730.0),
        "l6": (23.0, 115.0, 525.0, 718.0),
    },
}
# the paper's overall errors (eq. 27) on held-out positions
PAPER_OVERALL_ERROR = {
    "multi": {"l2": 0.0271, "l4": 0.0096, "l6": 0.0363},
    "l3": {"l2": 0.0309, "l4": 0.0126, "l6": 0.0451},
    "l5": {"l2": 0.1219, "l4": 0.0667, "l6": 0.0286},
}


def measured_modes(labels: tuple[str, ...], with_amplitudes: bool = True) -> MeasuredModes:
    """The paper's measured data at the given positions (amplitudes NaN where Table 2 has none)."""
    pos = np.array([POSITIONS_M[x] for x in labels])
    freq = np.array([MEASURED_FREQUENCIES_HZ[x] for x in labels])
    amp = np.array(
        [MEASURED_AMPLITUDES_M_PER_N.get(x, (NAN,) * 4) if with_amplitudes else (NAN,) * 4 for x in labels]
    )
    return MeasuredModes(pos, freq, amp)
