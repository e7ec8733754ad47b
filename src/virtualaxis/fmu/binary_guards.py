"""What the slave does so that the FMU's pythonfmu 0.7 binary does not corrupt its host's heap.

The binary (pythonfmu 0.7.0's ``PySlaveInstance.cpp``) frees memory that is still in use in three places; the host
process then dies later at a random point ("corrupted double-linked list", SIGABRT / SIGSEGV, mostly at exit):

- its interpreter state is a static ``std::shared_ptr`` that is reset again by a library destructor
  (``__attribute__((destructor))`` calling ``finalizePythonInterpreter``). At process exit the C++ static
  destructor runs first (``exit`` handlers come before ``_dl_fini``) and frees the shared state; the library
  destructor then resets the destroyed pointer, which decrements a counter inside the freed block: a write into
  the heap's free lists. In a host that owns the interpreter (FMPy, PyFMI: any Python process), the slave calls
  ``finalizePythonInterpreter`` itself when the interpreter exits (:func:`release_state_at_exit`), so both exit
  paths find the pointer empty. (When the FMU started the interpreter itself, in a host that is not Python, the
  state owns that interpreter and cannot be released from inside it.)

- each time it loads the slave class (``findClass``, at every ``fmi2Instantiate``) it executes the slave script
  in the module's namespace and then ``Py_DECREF``\\ s that namespace, a borrowed reference
  (``PyModule_GetDict``). The slave script holds one reference to its namespace each time it is executed
  (:func:`hold_namespace`), which balances it: the namespace is executed once per ``findClass`` (and once more
  at the first import: one reference kept for the process' life).
- when a slave method raises, it releases the slave class, the instance and its log queue, keeps the pointers,
  returns ``fmi2Fatal``, and releases them a second time in ``fmi2FreeInstance``. A slave method that raises to the
  binary first holds one reference to each (:func:`hold_for_error_exit`), so that the instance outlives the error
  and ``fmi2FreeInstance`` frees it once.

A binary without these defects only keeps the held references (a few small objects that live until the process
ends), so the slave stays correct with either.
"""

from __future__ import annotations

import atexit
import ctypes
import functools
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: the binaries whose interpreter state is released when the interpreter exits (path -> the loaded library)
_RELEASED_AT_EXIT: dict[str, ctypes.CDLL] = {}

#: the slave methods the binary calls with the instance (a raise from one of them is an error exit)
WRAPPER_CALLS = ("setup_experiment", "enter_initialization_mode", "exit_initialization_mode", "do_step",
                 "terminate", "get_integer", "get_real", "get_boolean", "get_string", "set_integer", "set_real",
                 "set_boolean", "set_string", "_get_fmu_state", "_set_fmu_state")


def hold(obj: object) -> None:
    """One more reference to ``obj``, never released."""
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(obj))


def hold_namespace(namespace: dict) -> None:
    """Called by the slave script at its top level with ``globals()`` (see the module docstring)."""
    hold(namespace)


def hold_for_error_exit(instance: Any) -> None:
    """What the binary releases when a method of ``instance`` raises: its class, the instance, its log queue."""
    hold(type(instance))
    hold(instance)
    hold(instance.log_queue)  # (the list the binary gets from pythonfmu's _get_log_queue)


def _guarded(method: Callable) -> Callable:
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except BaseException:
            hold_for_error_exit(self)
            raise
    return call


def guard_wrapper_calls(cls: type) -> type:
    """Class decorator: each method of :data:`WRAPPER_CALLS` holds back what the binary releases when it raises."""
    for name in WRAPPER_CALLS:
        setattr(cls, name, _guarded(getattr(cls, name)))
    return cls


def host_owns_interpreter() -> bool:
    """True when the interpreter was started on the process' main thread (a Python host, or a host that embeds
    Python itself); pythonfmu's binary starts it on a thread of its own."""
    return threading.main_thread().native_id == os.getpid()


def release_state_at_exit(binary: Path) -> bool:
    """Linux, interpreter owned by the host: release the interpreter state of the loaded FMU binary ``binary``
    (its ``finalizePythonInterpreter``) when the interpreter exits, before the C exit handlers run. Returns whether
    it is arranged (once per binary)."""
    if sys.platform != "linux" or not host_owns_interpreter():
        return False
    key = str(binary)
    if key not in _RELEASED_AT_EXIT:
        if not binary.is_file():
            return False
        lib = ctypes.CDLL(key)  # the binary the host loaded (the same path: the same library), kept loaded here
        release = getattr(lib, "finalizePythonInterpreter", None)
        if release is None:  # a binary without this state has nothing to release
            return False
        release.restype, release.argtypes = None, []
        _RELEASED_AT_EXIT[key] = lib
        atexit.register(release)
    return True
