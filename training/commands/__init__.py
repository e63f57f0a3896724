"""One module per ``twomass`` subcommand; each defines ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``. :mod:`training.cli` looks them up in its ``COMMANDS`` dict."""
