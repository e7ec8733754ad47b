import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: the folder every process of the session shares (the background runner, the session lock) and the session's
#: main process (the pytest-xdist controller, or the only pytest process)
SHARED = pytest.StashKey[Path]()
SESSION_PID = pytest.StashKey[int]()
OWNS_SHARED = pytest.StashKey[bool]()


def pytest_configure(config):
    """The ``virtual_axis`` fixture: from the ``pytest11`` entry point once the package is installed, otherwise
    registered here (never twice: pytest refuses a plugin registered under two names). The session's shared
    folder: made by the main process, handed to the pytest-xdist workers."""
    import virtualaxis.testing as plugin

    if not config.pluginmanager.is_registered(plugin):
        config.pluginmanager.register(plugin, "virtualaxis")
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None and "virtualaxis_shared" in workerinput:
        config.stash[SHARED] = Path(workerinput["virtualaxis_shared"])
        config.stash[SESSION_PID] = int(workerinput["virtualaxis_session_pid"])
        config.stash[OWNS_SHARED] = False
    else:
        config.stash[SHARED] = Path(tempfile.mkdtemp(prefix="virtualaxis-session-"))
        config.stash[SESSION_PID] = os.getpid()
        config.stash[OWNS_SHARED] = True


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """pytest-xdist hook (controller): each worker gets the session's shared folder."""
    node.workerinput["virtualaxis_shared"] = str(node.config.stash[SHARED])
    node.workerinput["virtualaxis_session_pid"] = str(node.config.stash[SESSION_PID])


def _workers(config) -> bool:
    return hasattr(config, "workerinput")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(session, config, items):
    """Tests marked ``@pytest.mark.background("job")`` run last; their jobs start now, once per session, in one
    SCHED_IDLE subprocess that uses the CPU the wall-clock-paced tests before them leave idle
    (tests/background.py). Under pytest-xdist (``--dist loadgroup``) a file's tests stay on one worker (its
    module fixtures are set up once), and a file's tests that wait for background jobs are a group of their own,
    scheduled last. Runs before xdist's own hook, which reads the groups."""
    import background

    wanted: list[str] = []
    late = []
    for item in items:
        marks = list(item.iter_markers("background"))
        if _workers(config):
            group = f"background-{item.path.name}" if marks else item.path.name
            item.add_marker(pytest.mark.xdist_group(name=group))
        if marks:
            late.append(item)
            for m in marks:
                for name in m.args:
                    if name not in background.JOBS:
                        raise pytest.UsageError(f"{item.nodeid}: unknown background job {name!r}")
                    if name not in wanted:
                        wanted.append(name)
    if not late or config.option.collectonly:
        return
    items[:] = [i for i in items if i not in late] + late
    background.start(config, config.stash[SHARED], config.stash[SESSION_PID], wanted)


def pytest_terminal_summary(terminalreporter):
    """How long the tests waited for the background jobs (0: the rest of the suite hid their computation)."""
    import background

    if background.WAITED_S:
        waits = ", ".join(f"{k} {v:.0f} s" for k, v in sorted(background.WAITED_S.items(), key=lambda kv: -kv[1]))
        terminalreporter.write_line(f"background jobs, waited for: {sum(background.WAITED_S.values()):.0f} s "
                                    f"({waits})")


def pytest_unconfigure(config):
    """The session's main process ends the background runner and removes the shared folder."""
    import background

    if config.stash.get(OWNS_SHARED, False):
        shared = config.stash[SHARED]
        background.stop(shared)
        shutil.rmtree(shared, ignore_errors=True)


@pytest.fixture(autouse=True)
def _exclusive_of_background(request):
    """Tests marked ``exclusive`` (timing-sensitive: a drive served at 1 ms, a master judging its answers) run
    one at a time across the pytest-xdist workers (tests/session_lock.py) and with the background computations
    stopped (tests/background.py). Beside them, the other worker runs ordinary tests: a CI runner with other
    work on it, which these tests must stand."""
    if request.node.get_closest_marker("exclusive") is None:
        yield
        return
    import background
    from session_lock import SessionLock

    with SessionLock(request.config.stash[SHARED]).exclusive():
        paused = background.pause(request.config)
        try:
            yield
        finally:
            if paused:
                background.resume(request.config)
