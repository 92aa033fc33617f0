"""Image queries on the base station: an encoded image (JPEG/PNG bytes from the client) →
its global feature in the language space of the map's feature space, which then scores the
map exactly like a text embedding (voxels, rays, clusters, search volume; the map side is
decompressed through the map's PCA and, for RADIO-space maps, mapped by the language head —
:meth:`common.feature_space.FeatureSpace.similarity`).

* **Label-encoder maps** (``encoder_name == "label"``, MiniLM space): the image's pixels are
  classified by the synthetic world's class appearance and the class-name embeddings mixed
  by their shares (:mod:`encoders.label_image` gives the exact definition); the class
  names are embedded by the map's text model, as the edge's label encoder embeds them.
* **NARADIO maps**: the mapper builds the same NARADIO the edge runs, from the edge's
  encoder settings in the feature space (``FeatureSpace.encoder_config``) and a RADIO
  checkpoint found in ``query.image_model_dir`` (default ``$RAYFRONTS_MODEL_DIR`` /
  ``~/.cache/rayfronts/models``, or ``encoder.checkpoint`` as the edge gave it); the
  checkpoint must be the edge's (its weight hash is part of the encoder version), else the
  query is refused. The image vector is the SigLIP head applied to the language teacher's
  class token (``encode_global``), i.e. the language space itself.

Decoding limits: the bytes must decode as an image (OpenCV: JPEG, PNG, ...) of at most
:data:`MAX_QUERY_PIXELS` pixels; every failure is one :class:`MessageError` line. Encoders
are cached per feature space (one NARADIO model per map space and device).
"""
from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from common.messages import MessageError

if TYPE_CHECKING:
    from common.feature_space import FeatureSpace
    from encoders.text.base import CachedTextEncoder

    #: the mapper's cached text-model factory: (name, device, model_dir) -> encoder
    TextEncoderFactory = Callable[[str, str | torch.device, str], CachedTextEncoder]

log = logging.getLogger("rayfronts.mapper")

#: query images larger than this (decoded H·W) are refused
MAX_QUERY_PIXELS = 4096 * 4096

_ENCODERS: dict = {}
_LOCK = threading.Lock()


def decode_query_image(data: bytes, max_pixels: int = MAX_QUERY_PIXELS) -> np.ndarray:
    """Encoded image bytes → ``(H, W, 3)`` uint8 RGB; :class:`MessageError` with the reason."""
    import cv2

    if not isinstance(data, (bytes, bytearray, memoryview)) or len(data) == 0:
        raise MessageError("query image is empty")
    buf = np.frombuffer(bytes(data), np.uint8)
    # read the size from the header first: refuse huge images before decoding their pixels
    hdr = _image_size(bytes(data[:65536]))
    if hdr is not None and hdr[0] * hdr[1] > max_pixels:
        raise MessageError(f"query image is {hdr[1]}x{hdr[0]} pixels, over the limit of {max_pixels} pixels")
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    if img is None:
        raise MessageError(f"query image ({len(data)} bytes) is not a decodable image (JPEG, PNG, ...)")
    if img.shape[0] * img.shape[1] > max_pixels:
        raise MessageError(f"query image is {img.shape[1]}x{img.shape[0]} pixels, over the limit of "
                           f"{max_pixels} pixels")
    return np.ascontiguousarray(img[..., ::-1])


def _image_size(head: bytes) -> tuple[int, int] | None:
    """``(H, W)`` from a PNG IHDR or the first JPEG SOF marker, else None (OpenCV decides)."""
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24:
        return int.from_bytes(head[20:24], "big"), int.from_bytes(head[16:20], "big")
    if head[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(head):
            if head[i] != 0xFF:
                return None
            m = head[i + 1]
            seg = int.from_bytes(head[i + 2:i + 4], "big")
            if m in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                return int.from_bytes(head[i + 5:i + 7], "big"), int.from_bytes(head[i + 7:i + 9], "big")
            i += 2 + seg
    return None


def embed_image(fs: FeatureSpace, data: bytes, device: str | torch.device = "cpu", text_model_dir: str = "",
                image_model_dir: str = "", text_encoder: TextEncoderFactory | None = None) -> torch.Tensor:
    """``(1, lang_dim)`` language-space vector of the encoded image ``data`` for space ``fs``
    (``text_encoder(name, device, model_dir)``: the mapper's cached text-model factory)."""
    rgb = decode_query_image(data)
    if fs.encoder_name == "label":
        return _label_vector(fs, rgb, device, text_model_dir, text_encoder)
    if fs.encoder_name == "naradio":
        enc = _naradio(fs, device, image_model_dir)
        with _LOCK, torch.inference_mode():
            g = enc.encode_global(rgb)
        return g.float().reshape(1, -1).to(device)
    raise MessageError(f"image queries are not available for {fs.encoder_name!r} feature spaces ({fs.id}): "
                       "send text or an embedding")


def _label_vector(fs, rgb, device, text_model_dir, text_encoder) -> torch.Tensor:
    from encoders.label_image import label_image_embedding, label_vocabulary

    key = ("label", fs.text_model, str(device), text_model_dir)
    with _LOCK:
        table = _ENCODERS.get(key)
        if table is None:
            if text_encoder is None:
                raise MessageError("no text encoder for the label space")
            te = text_encoder(fs.text_model, device, text_model_dir)
            table = te.encode_labels(label_vocabulary(), templates="none").float().cpu().numpy()
            _ENCODERS[key] = table
    if table.shape[1] != fs.lang_dim:
        raise MessageError(f"class embeddings are {table.shape[1]}-d, the map's language space {fs.lang_dim}-d")
    try:
        v = label_image_embedding(rgb, table)
    except ValueError as e:
        raise MessageError(f"query image: {e}") from None
    return torch.from_numpy(v).reshape(1, -1).to(device)


def _naradio(fs, device, image_model_dir: str):
    from common.model_files import ModelFileError
    from encoders.config import EncoderConfig
    from encoders.naradio import NaradioEncoder

    key = ("naradio", fs.id, str(device), image_model_dir)
    with _LOCK:
        enc = _ENCODERS.get(key)
        if enc is not None:
            return enc
        conf = dict(fs.encoder_config or {})
        if not conf:
            raise MessageError(f"feature space {fs.id} carries no encoder settings (an edge older than image "
                               "queries): restart the edge to serve them")
        if image_model_dir:
            conf["model_dir"] = image_model_dir
            conf["checkpoint"] = ""
        try:
            cfg = EncoderConfig(**{k: v for k, v in conf.items() if k in EncoderConfig.__dataclass_fields__})
            enc = NaradioEncoder(cfg, device=device)
        except (ModelFileError, ValueError, TypeError) as e:
            raise MessageError(f"image queries need the edge's RADIO model on the mapper: {e}") from None
        if enc.version != fs.encoder_version:
            raise MessageError(f"the mapper's RADIO model {enc.checkpoint_path} gives encoder version "
                               f"{enc.version}, the map's is {fs.encoder_version} (a different checkpoint or "
                               "settings): put the edge's checkpoint in query.image_model_dir")
        log.info("image queries: NARADIO %s loaded from %s", enc.version, enc.checkpoint_path)
        _ENCODERS[key] = enc
        return enc
