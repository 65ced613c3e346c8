"""The shape of a JSON request body, checked before FastAPI parses and validates it.

A body under the size limit (`service.api.uploads.BodyLimit`) can still hold a great
many keys: 1 MB of them took pydantic seconds to refuse (each extra key an error), on
the event loop, and every other request of every tenant waited meanwhile. `JsonShape`
reads the body and counts its colons, commas and brackets, which bound its keys,
values and depth: more colons than keys allowed, or commas than values, is refused at
once; a body with more brackets than the depth allowed is parsed in a worker thread (one
at a time: the parse holds the GIL the event loop needs; such a body is small by then)
and its depth measured;
a body past `MAX_KEYS`, `MAX_VALUES` or `MAX_DEPTH` is answered 422 at once, signed
in or not, without reaching validation. A body within them is handed on as it came
(its parse again in FastAPI is quick: it is small in structure).
"""

from __future__ import annotations

import asyncio
import json

from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from service.errors import TooLargeError

#: keys of all the objects in one body (a job's parameters have a few dozen)
MAX_KEYS = 1000
#: values (object members and array items) in one body
MAX_VALUES = 10_000
#: objects and arrays nested in one another
MAX_DEPTH = 16


def shape_problem(value, *, max_keys: int = MAX_KEYS, max_values: int = MAX_VALUES, max_depth: int = MAX_DEPTH) -> str | None:
    """What makes a parsed JSON value too big in structure, or None."""
    keys = values = 0
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children = item.values()
            keys += len(item)
        elif isinstance(item, list):
            children = item
        else:
            continue
        if depth > max_depth:
            return f"the request body nests objects and arrays more than {max_depth} deep"
        values += len(children)
        if keys > max_keys:
            return f"the request body has more than {max_keys} keys"
        if values > max_values:
            return f"the request body has more than {max_values} values"
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))
    return None


def _count_problem(body: bytes) -> str | None:
    """What the body's bytes alone show past the limits: every key has a colon after
    it and every value after the first a comma or a colon before it, so more colons than
    `MAX_KEYS` or more commas than `MAX_VALUES` is a body past them (a colon or comma
    inside a string counts too: no request of this API has a string near that long).
    No parse: a 1 MB body of keys took 45 ms of the GIL to parse, the event loop's too."""
    colons = body.count(b":")
    if colons > MAX_KEYS:
        return f"the request body has more than {MAX_KEYS} keys (colons)"
    if body.count(b",") + colons + 1 > MAX_VALUES:
        return f"the request body has more than {MAX_VALUES} values (commas)"
    return None


def _surely_small(body: bytes) -> bool:
    """True when the bytes show the body within the limits without a parse (its keys
    and values are within them by `_count_problem`; so is its depth with no more than
    `MAX_DEPTH` brackets)."""
    return body.count(b"{") + body.count(b"[") <= MAX_DEPTH


def _check(body: bytes) -> str | None:
    problem = _count_problem(body)
    if problem or _surely_small(body):
        return problem
    try:
        # a nesting deeper than Python's recursion limit fails json.loads itself
        value = json.loads(body)
    except RecursionError:
        return f"the request body nests objects and arrays more than {MAX_DEPTH} deep"
    except ValueError:
        return None  # malformed: FastAPI says where, as for any body
    return shape_problem(value)


def _is_json(scope) -> bool:
    for key, value in scope.get("headers", ()):
        if key == b"content-type":
            media = value.split(b";", 1)[0].strip().lower()
            return media == b"application/json" or media.endswith(b"+json")
    return False


class JsonShape:
    """ASGI middleware: 422 for a JSON body past the limits above, checked off the event loop."""

    def __init__(self, app) -> None:
        self.app = app
        self._parsing = None  # one parse at a time: the GIL is shared with the event loop

    async def _shape(self, body: bytes) -> str | None:
        problem = _count_problem(body)
        if problem or _surely_small(body):
            return problem
        if self._parsing is None:
            self._parsing = asyncio.Semaphore(1)
        async with self._parsing:
            return await run_in_threadpool(_check, body)

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http" or scope.get("method") not in ("POST", "PUT", "PATCH") or not _is_json(scope):
            await self.app(scope, receive, send)
            return
        chunks, messages = [], []
        try:
            while True:
                message = await receive()
                messages.append(message)
                if message["type"] != "http.request":
                    break
                chunks.append(message.get("body", b""))
                if not message.get("more_body", False):
                    break
        except TooLargeError as exc:  # (from BodyLimit, outside the app's error handlers)
            await JSONResponse({"detail": exc.detail}, status_code=413, headers={"Connection": "close"})(scope, receive, send)
            return
        body = b"".join(chunks)
        problem = await self._shape(body)
        if problem:
            await JSONResponse({"detail": problem + "; send only the fields the API documents"},
                               status_code=422)(scope, receive, send)
            return
        replay = iter(messages)

        async def replayed():
            for message in replay:
                return message
            return await receive()

        await self.app(scope, replayed, send)
