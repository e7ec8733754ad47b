"""Reference axis written apart from the diagnosed model.

Its own equations, integrator (RK4 + exact bristle and actuator-lag updates, 31.25 us), controller
discretisation and sensor models; it imports nothing from ``virtualaxis.sim``, ``plant``, ``control`` or
``diagnosis`` (checked by ``tests/test_refaxis.py``). The gap bench uses it through::

    from virtualaxis.refaxis import case_names, make_case
    names = case_names("two_mass")            # ["two_mass/clean", "two_mass/backlash", ...]
    cf = make_case("two_mass/backlash", out_dir, seed=0, quick=False)
    cf.config_path, cf.fit, cf.holdout, cf.truth

See docs/refaxis.md for the equations, the cases and their magnitudes.
"""

from virtualaxis.refaxis.cases import CaseFiles, CaseSpec, case_names, make_case

STRUCTURES = ("two_mass", "full_closed", "rigid_pp")

__all__ = ["CaseFiles", "CaseSpec", "STRUCTURES", "case_names", "make_case"]
