"""Sim-to-real gap diagnosis: where the gap lies, which unmodelled effect causes it, how far it shrinks.

Modules: :mod:`trace` (reading/validating measured traces), :mod:`where` (residual localisation),
:mod:`effects` (the candidate-effect library), :mod:`fit` (fitting one candidate), :mod:`selection` (forward
selection as stages), :mod:`hybrid` (data-driven residual models), :mod:`pipeline` (the whole diagnosis as
stages), :mod:`report`
(report.json / report.html / calibrated.toml) and :mod:`bench` (withheld-effect gap bench).
"""

from typing import TYPE_CHECKING

from virtualaxis.lazy import lazy_exports

if TYPE_CHECKING:
    from virtualaxis.diagnosis.effects import EFFECTS
    from virtualaxis.diagnosis.pipeline import NO_EFFECT, DiagnosisResult, run_diagnosis, write_outputs
    from virtualaxis.diagnosis.trace import Trace, read_trace

# imported on first use (virtualaxis.lazy): a submodule such as diagnosis.trace loads without the fitting stack
__getattr__, __dir__ = lazy_exports(__name__, {
    "EFFECTS": "virtualaxis.diagnosis.effects",
    **{n: "virtualaxis.diagnosis.pipeline" for n in ("NO_EFFECT", "DiagnosisResult", "run_diagnosis",
                                                     "write_outputs")},
    **{n: "virtualaxis.diagnosis.trace" for n in ("Trace", "read_trace")},
}, globals())

__all__ = ["EFFECTS", "NO_EFFECT", "DiagnosisResult", "Trace", "read_trace", "run_diagnosis", "write_outputs"]
