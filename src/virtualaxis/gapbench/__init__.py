"""Gap bench on an independent reference axis: withheld-effect cases made by ``virtualaxis.refaxis`` (its own
equations, integrator and controller discretisation), diagnosed by ``virtualaxis.diagnosis``, scored against
the case's truth. This package is the only place that imports both; the diagnosis never sees the reference's
code or truth."""

from virtualaxis.gapbench.reference import evaluate_reference_case, run_reference_bench, summarise_reference

__all__ = ["evaluate_reference_case", "run_reference_bench", "summarise_reference"]
