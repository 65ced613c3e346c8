"""One module per ``orchard`` sub-command. Each defines ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``; :mod:`service.cli` registers
every module listed in ``COMMANDS``.

``orchard --help`` imports every command module (for its name and help line), so a
command module imports at its top only what costs next to nothing; its libraries
(pydantic-settings ~0.3 s, numpy ~0.35 s, the store ~0.07 s, dask ~1 s, matplotlib
~1-2 s, measured with ``python -X importtime``) are imported in the function that needs
them, under a one-line comment that says so."""

COMMANDS = ["demo", "process", "convert", "simulate", "evaluate", "serve", "tokens", "tenants", "schedules", "blocks"]
