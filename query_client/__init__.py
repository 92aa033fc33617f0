"""Operator part: the query command line and the Python client API planners import."""
