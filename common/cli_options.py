"""Command-line helpers shared by the role programs (``rayfronts edge``, ``mapper``, ...)."""
from __future__ import annotations

import argparse
from typing import Callable


def split_trailing_options(args: argparse.Namespace, items: list[str],
                           add_options: Callable[..., None]) -> list[str]:
    """argparse stops at the first positional ``key=value`` item: parse the options written
    after the items onto ``args`` (``add_options(parser, suppress=True)`` declares them) and
    return the remaining ``key=value`` overrides. Unknown options are a ConfigError."""
    p = argparse.ArgumentParser(add_help=False)
    add_options(p, suppress=True)
    ns, rest = p.parse_known_args(items)
    for k, v in vars(ns).items():
        setattr(args, k, v)
    bad = [r for r in rest if r.startswith("-")]
    if bad:
        from common.config import ConfigError

        raise ConfigError(f"unknown option(s) {bad}")
    return rest
