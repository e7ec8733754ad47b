"""The axis as an FMI co-simulation FMU (``virtualaxis fmu``; docs/fmu.md)."""

from virtualaxis.fmu.export import INTERFACES, FmuExportError, build_fmu

__all__ = ["INTERFACES", "FmuExportError", "build_fmu"]
