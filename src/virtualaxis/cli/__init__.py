"""The ``virtualaxis`` command line. Each command is a module here with ``register(subparsers)``."""
