"""One module per ``orchard`` sub-command. Each defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :mod:`service.cli` registers
every module listed in ``COMMANDS``."""

COMMANDS = ["demo", "process", "convert", "simulate", "evaluate", "serve", "tokens", "tenants", "schedules", "blocks"]
