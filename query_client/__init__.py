"""Operator part: the query command line and the Python client API planners import."""
from __future__ import annotations


def __getattr__(name):  # lazy: importing the package does not open zenoh
    if name in ("Client", "QueryError", "MapperUnavailable", "WatchHandle"):
        from query_client import client

        return getattr(client, name)
    if name == "QueryResult":
        from common.messages import QueryResult

        return QueryResult
    raise AttributeError(name)


__all__ = ["Client", "QueryResult", "QueryError", "MapperUnavailable", "WatchHandle"]
