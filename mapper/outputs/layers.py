"""Layer messages of the mapper: voxels, frontiers, rays, occupancy stats, published on
``<prefix>/mapper/layers/<layer>`` at ``layers.rate_hz`` by the map worker and answered on a
``get`` of the same key (module map: :mod:`mapper.state`; ARCHITECTURE.md).

Layers are subsampled to ``layers.max_voxels`` / ``layers.max_rays`` (seeded, stable) by
:func:`mapper.service_map.layer_arrays`; the message is :func:`common.messages.encode_layer`.
Other outputs that follow the layers (rerun, later ROS) are called from :meth:`LayerPublisher.publish`.
"""
from __future__ import annotations

import logging
import time

from common.messages import LAYERS, MessageError, encode_error, encode_layer
from mapper.state import MapperState

log = logging.getLogger("rayfronts.mapper")


class LayerPublisher:
    """Builds and publishes layer messages; ``followers`` get ``layers_published()`` after each put."""

    def __init__(self, state: MapperState, followers=()):
        self.state = state
        self.followers = list(followers)

    def layer_bytes(self, layer: str) -> bytes:
        from mapper.service_map import layer_arrays

        s = self.state
        with s.lock:
            if s.map is None:
                raise MessageError("no map yet")
            arrays, meta = layer_arrays(s.map, layer, s.cfg.layers)
        meta.update(frames_mapped=s.mapped, stamp=time.time())
        return encode_layer(layer, arrays, meta)

    def publish(self) -> None:
        s = self.state
        for layer in LAYERS:
            try:
                s.session.put(s.keys.layers(layer), self.layer_bytes(layer))
            except Exception as e:
                s.warn("layers", "publishing layer %s failed: %s", layer, e)
        for f in self.followers:
            f.layers_published()

    def on_layer_get(self, query) -> None:
        try:
            layer = str(query.key_expr).rsplit("/", 1)[-1]
            try:
                payload = self.layer_bytes(layer)
            except MessageError as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("layer query failed: %s", e)
