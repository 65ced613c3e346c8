"""The API document: one operationId per operation, the same on every start.

FastAPI names an operation ``<function><path>_<method>``, but a route taking several
methods (``GET`` and ``HEAD`` on a download) gets one name for all of them, ending in
whichever method its set yields first: duplicate ids (generated clients break on them)
that change with the interpreter's hash seed. Here each operation of such a route is
named with its own method; operations of one-method routes keep FastAPI's names.
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from typing import Any

from fastapi import FastAPI

_METHODS = ("get", "put", "post", "delete", "options", "head", "patch", "trace")
_METHOD_SUFFIX = re.compile(r"_(?:%s)$" % "|".join(_METHODS))


def unique_operation_ids(schema: dict[str, Any]) -> dict[str, Any]:
    """Rename, in ``schema`` (an OpenAPI document), the operations whose operationId is
    shared: each becomes its id without the method suffix plus its own method."""
    ops = [(op, method) for item in schema.get("paths", {}).values()
           for method, op in item.items() if method in _METHODS and isinstance(op, dict)]
    counts = Counter(op.get("operationId") for op, _ in ops)
    for op, method in ops:
        if counts[op.get("operationId")] > 1:
            op["operationId"] = f"{_METHOD_SUFFIX.sub('', op['operationId'])}_{method}"
    return schema


def install(app: FastAPI) -> None:
    """Serve ``app``'s document with unique, stable operationIds (see the module docstring)."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            with warnings.catch_warnings():  # FastAPI warns of the duplicates renamed here
                warnings.filterwarnings("ignore", message="Duplicate Operation ID")
                app.openapi_schema = unique_operation_ids(generate())
        return app.openapi_schema

    app.openapi = openapi
