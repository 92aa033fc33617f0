"""Image resampling and decoding helpers shared by the frame sources.

Sizes are ``(height, width)``. Nearest resampling samples at pixel centres (like torch's
``nearest-exact``) so it is exact for integer scale factors and keeps NaN / +inf and
label ids untouched.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from edge.sources.errors import SourceError


def parse_resolution(res: str | None) -> tuple[int, int] | None:
    """``"HxW"`` → ``(H, W)``; ``None`` / ``""`` → ``None`` (native)."""
    if res is None or str(res).strip() == "":
        return None
    m = re.fullmatch(r"\s*(\d+)\s*[xX×,]\s*(\d+)\s*", str(res))
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise SourceError(f"resolution {res!r} is not of the form 'HxW' with positive integers, e.g. '240x320'")
    return int(m.group(1)), int(m.group(2))


def resize_nearest(img: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Nearest resampling at pixel centres of an (H, W, ...) array of any dtype."""
    h, w = img.shape[:2]
    if (h, w) == tuple(hw):
        return img
    rows = np.minimum(((np.arange(hw[0]) + 0.5) * (h / hw[0])).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(hw[1]) + 0.5) * (w / hw[1])).astype(np.int64), w - 1)
    return img[rows[:, None], cols[None, :]]


def resize_rgb(rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W, 3) uint8 image: area filter when shrinking (anti-aliased), bilinear otherwise."""
    h, w = rgb.shape[:2]
    if (h, w) == tuple(hw):
        return rgb
    interp = cv2.INTER_AREA if hw[0] <= h and hw[1] <= w else cv2.INTER_LINEAR
    return cv2.resize(rgb, (hw[1], hw[0]), interpolation=interp)


def _check_file(path: Path) -> Path:
    if not path.is_file():
        raise SourceError(f"missing file: {path}")
    return path


def read_rgb(path: Path) -> np.ndarray:
    """Read a colour image file → (H, W, 3) uint8 RGB."""
    img = cv2.imread(str(_check_file(path)), cv2.IMREAD_COLOR)
    if img is None:
        raise SourceError(f"cannot decode image {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_png_unchanged(path: Path, dtypes: tuple[type, ...] = (np.uint8, np.uint16)) -> np.ndarray:
    """Read a PNG with its stored depth and channels (``IMREAD_UNCHANGED``)."""
    img = cv2.imread(str(_check_file(path)), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SourceError(f"cannot decode image {path}")
    if img.dtype not in dtypes:
        raise SourceError(f"{path}: unexpected pixel type {img.dtype}")
    return img


def read_depth_u16(path: Path, scale: float) -> np.ndarray:
    """uint16 depth PNG → float32 metres (``value / scale``); 0 stays 0 (sanitised to NaN later)."""
    img = read_png_unchanged(path, dtypes=(np.uint16,))
    if img.ndim != 2:
        raise SourceError(f"{path}: depth PNG must be single-channel 16-bit, got shape {img.shape}")
    return img.astype(np.float32) / np.float32(scale)


def decode_rgba_float32(bgra: np.ndarray) -> np.ndarray:
    """Float32 values packed little-endian into the 4 bytes (R, G, B, A) of an RGBA PNG.

    ``bgra`` is what ``cv2.imread(..., IMREAD_UNCHANGED)`` returns: (H, W, 4) uint8 in
    OpenCV's B, G, R, A order, so the bytes are reordered to R, G, B, A before the view."""
    if bgra.ndim != 3 or bgra.shape[2] != 4 or bgra.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 4) uint8 BGRA image, got {bgra.shape} {bgra.dtype}")
    rgba = np.ascontiguousarray(bgra[..., [2, 1, 0, 3]])
    return rgba.view("<f4")[..., 0].astype(np.float32)


def encode_float32_rgba(depth: np.ndarray) -> np.ndarray:
    """Inverse of :func:`decode_rgba_float32`: (H, W) float32 → (H, W, 4) uint8 BGRA for ``cv2.imwrite``."""
    d = np.ascontiguousarray(np.asarray(depth, dtype="<f4"))
    rgba = d.view(np.uint8).reshape(*d.shape, 4)
    return np.ascontiguousarray(rgba[..., [2, 1, 0, 3]])
