"""Query parameters a route does not take are refused (422 naming them), not ignored:
`?rows=5` for `?row=5` would otherwise answer every tree as if filtered."""

from __future__ import annotations

from fastapi import Request

from pipeline.errors import ParameterError


def _query_names(dependant):
    """The query parameters of a route's dependant and of its dependencies."""
    yield from (p.alias for p in dependant.query_params)
    for sub in dependant.dependencies:
        yield from _query_names(sub)


def _accepted(route) -> set[str]:
    names = getattr(route, "_orchard_query_names", None)
    if names is None:
        names = set(_query_names(route.dependant))
        route._orchard_query_names = names  # the route's parameters never change: read once
    return names


def no_unknown_query(request: Request) -> None:
    """ParameterError (422) when the request's query names a parameter its route does not take."""
    route = request.scope.get("route")
    if route is None or not request.query_params:
        return
    unknown = sorted(set(request.query_params) - _accepted(route))
    if unknown:
        names = ", ".join(repr(u) for u in unknown)
        raise ParameterError(f"unknown query parameter(s) {names}; this route takes: "
                             f"{', '.join(sorted(_accepted(route))) or 'none'}", param=unknown[0])
