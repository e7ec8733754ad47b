"""Children with the default reaction to the terminal's signals.

A shell starts a background job (``cmd &``) with SIGINT and SIGQUIT ignored and ``nohup`` ignores SIGHUP; ignored
signals stay ignored across ``exec``, and Python then installs no handler for them. A test that sends these
signals to a command gives the command the dispositions it has when a user starts it from a terminal, whatever
started pytest.
"""

import signal

TERMINAL_SIGNALS = (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP)


def default_terminal_signals() -> None:
    """``preexec_fn`` of a child: SIGINT, SIGQUIT and SIGHUP back to their default action."""
    for sig in TERMINAL_SIGNALS:
        signal.signal(sig, signal.SIG_DFL)
