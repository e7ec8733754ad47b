"""The CLI's user-facing error (its own module, so that ``python -m virtualaxis.cli.main`` and the installed
``virtualaxis`` command share one class)."""


class CliError(Exception):
    """A user-facing error with a one-line message."""


class StdoutError(OSError):
    """Standard output could not be written (``> /dev/full``, a full disk, a closed terminal)."""
