import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def pytest_configure(config):
    """The ``virtual_axis`` fixture: from the ``pytest11`` entry point once the package is installed, otherwise
    registered here (never twice: pytest refuses a plugin registered under two names)."""
    import virtualaxis.testing as plugin

    if not config.pluginmanager.is_registered(plugin):
        config.pluginmanager.register(plugin, "virtualaxis")
