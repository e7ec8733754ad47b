import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_configure(config):
    """The ``virtual_axis`` fixture: from the ``pytest11`` entry point once the package is installed, otherwise
    registered here (never twice: pytest refuses a plugin registered under two names)."""
    import virtualaxis.testing as plugin

    if not config.pluginmanager.is_registered(plugin):
        config.pluginmanager.register(plugin, "virtualaxis")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(session, config, items):
    """Tests marked ``@pytest.mark.background("job")`` run last; their jobs start now, in one SCHED_IDLE
    subprocess that uses the CPU the wall-clock-paced tests before them leave idle (tests/background.py)."""
    import background

    wanted: list[str] = []
    late = []
    for item in items:
        marks = list(item.iter_markers("background"))
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
    background.start(config, wanted)


def pytest_unconfigure(config):
    import background

    background.stop(config)


@pytest.fixture(autouse=True)
def _exclusive_of_background(request):
    """Tests marked ``exclusive`` (timing-sensitive: a drive served at 1 ms, a master judging its answers) run
    with the background computations stopped (tests/background.py)."""
    if request.node.get_closest_marker("exclusive") is None:
        yield
        return
    import background

    paused = background.pause(request.config)
    try:
        yield
    finally:
        if paused:
            background.resume(request.config)
