"""Layer messages of the mapper: voxels, frontiers, rays, occupancy stats, published on
``<prefix>/mapper/layers/<layer>`` at ``layers.rate_hz`` by the map worker and answered on a
``get`` of the same key (module map: ARCHITECTURE.md).

Layers are subsampled to ``layers.max_voxels`` / ``layers.max_rays`` (seeded, stable) by
:func:`mapper.service_map.layer_arrays`; the message is :func:`common.messages.encode_layer`.
Other outputs that follow the layers (rerun, later ROS) are called from :meth:`LayerPublisher.publish`.
"""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from common.messages import LAYERS, MessageError, encode_error, encode_layer
from mapper.state import MapperState

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger("rayfronts.mapper")


class LayerPublisher:
    """Builds and publishes layer messages; ``followers`` get ``layers_published()`` after each put."""

    def __init__(self, state: MapperState, followers=()):
        self.state = state
        self.followers = list(followers)

    def layer_bytes(self, layer: str) -> bytes:
        from mapper.service_map import layer_arrays

        state = self.state
        with state.lock:
            if state.map is None:
                raise MessageError("no map yet")
            arrays, meta = layer_arrays(state.map, layer, state.cfg.layers)
        meta.update(frames_mapped=state.mapped, stamp=time.time())
        return encode_layer(layer, arrays, meta)

    def publish(self) -> None:
        state = self.state
        for layer in LAYERS:
            try:
                assert state.session is not None and state.keys is not None    # started
                state.session.put(state.keys.layers(layer), self.layer_bytes(layer))
            except Exception as e:
                state.warn("layers", "publishing layer %s failed: %s", layer, e)
        for f in self.followers:
            f.layers_published()

    def on_layer_get(self, query: zenoh.Query) -> None:
        try:
            layer = str(query.key_expr).rsplit("/", 1)[-1]
            try:
                payload = self.layer_bytes(layer)
            except MessageError as e:
                payload = encode_error(str(e))
            query.reply(query.key_expr, payload)
        except Exception as e:
            log.warning("layer query failed: %s", e)
