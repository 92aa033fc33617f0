"""Answering a mapper queryable: one reply per Zenoh query, errors as one line."""
from __future__ import annotations

import collections
import logging
from typing import Any, Callable

from common.messages import MessageError, encode_error

log = logging.getLogger("rayfronts.mapper")

#: requests answered with an error, by what was asked ("search", "query", ...; stats "request_errors")
REQUEST_ERRORS: collections.Counter = collections.Counter()


def reply_to(query: Any, what: str, answer: Callable[[bytes], bytes],
             attachment: Callable[[], bytes | None] | None = None) -> None:
    """Reply to a Zenoh query with ``answer(payload)``; a bad request (``MessageError``,
    ``ValueError``) becomes an encoded one-line error, a bug an "internal error" line; with
    ``attachment``, its value (taken after answering) rides along. Never raises (it runs on a
    Zenoh thread)."""
    try:
        try:
            if query.payload is None:
                raise MessageError(f"{what} without payload")
            payload = answer(query.payload.to_bytes())
        except (MessageError, ValueError) as e:
            REQUEST_ERRORS[what] += 1
            payload = encode_error(str(e))
        except Exception as e:
            REQUEST_ERRORS[what] += 1
            log.exception("%s failed", what)
            payload = encode_error(f"internal error: {e!r}")
        if attachment is not None:
            query.reply(query.key_expr, payload, attachment=attachment())
        else:
            query.reply(query.key_expr, payload)
    except Exception as e:
        log.warning("%s callback: %s", what, e)
