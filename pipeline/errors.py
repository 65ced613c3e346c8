"""Domain errors. They carry no HTTP status, exit code or command-line wording: the
service and the command line each word and map them in one place. Messages say what
was wrong and what to do.

A message names the parameters it is about as ``{path}`` placeholders, a path in the
job's parameters: ``{tiling.buffer}``, ``{trunks.min_tree_height}`` (a group of
:class:`pipeline.params.PipelineParams` and its field), or ``{job.work_dir}`` (a
setting of the run: ``job.input_path``, ``job.out_dir``, ``job.work_dir``,
``job.resume``, ``job.scheduler``). Each edge words them: the command line as options
(``--buffer``), the API as request fields (``tiling.buffer``).
"""

from __future__ import annotations

import copy
import re
from typing import Any, Callable

#: ``{group.field}``: a parameter named in a message (lower-case words joined by dots)
_PLACEHOLDER = re.compile(r"\{([a-z][a-z0-9_]*(?:\.[a-z][a-z0-9_]*)+)\}")


class OrchardError(Exception):
    """Base class of every error a user can cause.

    Parameters
    ----------
    message : str
        What was wrong, with the parameters it names as ``{path}`` placeholders.
    param : str, optional
        Path of the parameter at fault (``tiling.buffer``).
    value, limit : optional
        Its value and the bound it broke (same unit as the parameter).
    hint : str
        What to do, worded as ``message``; shown after it.
    """

    def __init__(self, message: str = "", *, param: str | None = None, value: Any = None, limit: Any = None,
                 hint: str = "") -> None:
        super().__init__(message + hint)
        self.message, self.param, self.value, self.limit, self.hint = message, param, value, limit, hint

    def render(self, name: Callable[[str], str | None], *, hint: bool = True) -> str:
        """The message (and ``hint``) with each parameter worded by ``name(path)``
        (None: the path as it is)."""
        text = self.message + (self.hint if hint else "")
        return _PLACEHOLDER.sub(lambda m: name(m.group(1)) or m.group(1), text)

    def __str__(self) -> str:
        return self.render(lambda path: path)

    def prefixed(self, prefix: str) -> OrchardError:
        """This error, of its class and fields, with ``prefix`` (where it happened) before its message."""
        exc = copy.copy(self)
        exc.message = prefix + self.message
        exc.args = (prefix + self.message + self.hint,)
        return exc

    def __reduce__(self):
        # back from a dask worker with its fields, whatever the subclass's own arguments
        return _restore, (type(self), self.args, self.__dict__)


def _restore(cls: type[OrchardError], args: tuple, fields: dict) -> OrchardError:
    exc = cls.__new__(cls)
    Exception.__init__(exc, *args)
    exc.__dict__.update(fields)
    return exc


class InputError(OrchardError):
    """The input file is not usable: not LAS/LAZ, truncated, empty, bad coordinates."""


class ParameterError(OrchardError):
    """Parameters are out of range or inconsistent (e.g. a buffer smaller than the reach)."""


class NoTreesError(OrchardError):
    """The block was read and processed but holds no trees (e.g. only ground)."""


class NoOverlapError(ParameterError):
    """Two captures of a block do not overlap: no credible rigid transform maps the trees
    of ``capture`` onto those of ``previous`` (both capture ids, as fields)."""

    def __init__(self, message: str = "", *, capture: str | None = None, previous: str | None = None,
                 n_matched: int = 0, hint: str = "", **fields) -> None:
        super().__init__(message, hint=hint, **fields)
        self.capture, self.previous, self.n_matched = capture, previous, n_matched
