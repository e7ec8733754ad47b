"""Numba's on-disk cache failing to save or load never fails a computation (virtualaxis.jitcache)."""

from __future__ import annotations

import importlib.util
import logging

from numba.core import caching

import virtualaxis.jitcache  # noqa: F401  (installs the guard)


def _fresh_module(tmp_path, name: str):
    src = tmp_path / f"{name}.py"
    src.write_text("from numba import njit\n\n@njit(cache=True)\ndef twice(x):\n    return 2.0 * x\n")
    spec = importlib.util.spec_from_file_location(name, src)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_failed_cache_save_is_logged_and_the_call_goes_on(tmp_path, monkeypatch, caplog):
    def broken_save(self, sig, data):  # what CI saw when several processes compiled at once
        raise RuntimeError("no compiled object yet for <Library 'twice'>")

    monkeypatch.setattr(caching.Cache, "_save_overload", broken_save)
    mod = _fresh_module(tmp_path, "jit_save_case")
    with caplog.at_level(logging.WARNING, logger="virtualaxis.jitcache"):
        assert mod.twice(1.25) == 2.5
    assert any("not saved" in r.getMessage() and "no compiled object yet" in r.getMessage() for r in caplog.records)


def test_a_failed_cache_load_is_a_miss(tmp_path, monkeypatch, caplog):
    mod = _fresh_module(tmp_path, "jit_load_case")
    assert mod.twice(2.0) == 4.0  # compiled and saved
    mod2 = _fresh_module(tmp_path, "jit_load_case")  # a new process would load it: make the load fail

    def broken_load(self, sig, target_context):
        raise EOFError("half-written cache entry")

    monkeypatch.setattr(caching.Cache, "_load_overload", broken_load)
    with caplog.at_level(logging.WARNING, logger="virtualaxis.jitcache"):
        assert mod2.twice(3.0) == 6.0
    assert any("not loaded" in r.getMessage() for r in caplog.records)
