"""Domain errors. They carry no HTTP status or exit code: the service and the
command line each map them in one place. Messages say what was wrong and what to do."""


class OrchardError(Exception):
    """Base class of every error a user can cause."""


class InputError(OrchardError):
    """The input file is not usable: not LAS/LAZ, truncated, empty, bad coordinates."""


class ParameterError(OrchardError):
    """Parameters are out of range or inconsistent (e.g. a buffer smaller than the reach)."""


class NoTreesError(OrchardError):
    """The block was read and processed but holds no trees (e.g. only ground)."""
