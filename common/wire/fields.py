"""Field-level checks shared by the frame codec and the image codecs (``common.wire`` package).

``_enc_err`` / ``_err`` format the one-line error of an encode / decode failure naming the
field (``cannot encode frame: <field>: ...`` / ``frame.<field>: ...``); the rest check one
decoded header value's type, dtype, rank or size and raise that error.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from common.wire.envelope import WireError, WireLimits, _tname


def _enc_err(field: str, msg: str) -> WireError:
    return WireError(f"cannot encode frame: {field}: {msg}")


def _as_array(x: Any, field: str) -> np.ndarray:
    try:
        return np.asarray(x)
    except Exception as e:
        raise _enc_err(field, f"not array-like ({e})") from e



def _err(field: str, msg: str) -> WireError:
    return WireError(f"frame.{field}: {msg}")



def _req(body: dict, key: str) -> Any:
    if key not in body:
        raise _err(key, "required field missing")
    return body[key]


def _nd(x: Any, field: str, dtype: str, ndim: int) -> np.ndarray:
    if type(x) is not np.ndarray:
        raise _err(field, f"expected an array, got {_tname(x)}")
    if x.dtype.str != dtype or x.ndim != ndim:
        raise _err(field, f"expected a {ndim}-D {dtype} array, got {x.ndim}-D {x.dtype.str} shape {x.shape}")
    return x


def _image_spec(body: dict, field: str, keys: tuple[str, ...]) -> dict:
    if field not in body:
        raise _err(field, "required field missing")
    spec = body[field]
    if type(spec) is not dict:
        raise _err(field, f"expected a map with keys {list(keys)}, got {_tname(spec)}")
    for k in keys:
        if k not in spec:
            raise _err(f"{field}.{k}", "required field missing")
    if type(spec["codec"]) is not str:
        raise _err(f"{field}.codec", f"expected str, got {_tname(spec['codec'])}")
    return spec


def _shape(x: Any, field: str, n: int, lim: WireLimits) -> list[int]:
    if type(x) is not list or len(x) != n or any(type(s) is not int or s < 1 for s in x):
        raise _err(field, f"expected {n} ints >= 1, got {x!r:.100}")
    if x[0] * x[1] > lim.max_pixels:
        raise _err(field, f"{x[0]}x{x[1]} pixels is over the limit {lim.max_pixels}")
    return x


def _bytes_array(x: Any, field: str) -> np.ndarray:
    a = _nd(x, field, "|u1", 1)
    if a.size == 0:
        raise _err(field, "empty")
    return a

